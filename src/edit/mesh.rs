//! Export of a field (or one object of it) as a triangle mesh: marching cubes
//! over the *activated* density, then binary PLY or binary glTF (`.glb`).
//!
//! Marching cubes uses the classic Lorensen–Cline / Bourke triangle table
//! (from the `marching-cubes` crate) with its corner and edge numbering:
//! corners `(0,0,0) (1,0,0) (1,1,0) (0,1,0) (0,0,1) (1,0,1) (1,1,1) (0,1,1)`,
//! edges 0–3 around the lower face, 4–7 around the upper face, 8–11 upright.
//! A table bit is set for a corner *outside* the surface (σ ≤ iso); with that
//! choice the table's triangles wind counter-clockwise seen from outside.
//!
//! The grid is padded with one layer of empty points on every side, so a
//! surface that touches the box is closed by a cap on the box face. Every
//! grid edge that the surface crosses owns exactly one vertex (its index is
//! the edge's rank among crossing edges), so neighbouring cubes share vertices
//! and a closed surface is watertight by construction.

use crate::error::{Error, Result};
use crate::field::{Bitmap, Field, GridGeom, RankIndex};
use glam::{Affine3A, Vec3};
use marching_cubes::tables::TRI_TABLE;
use rayon::prelude::*;
use std::path::Path;

/// A triangle mesh as plain arrays. Triangles wind counter-clockwise seen
/// from outside; normals point outwards; colours are linear RGB in [0, 1].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub positions: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    pub colors: Vec<[f32; 3]>,
    /// Three vertex indices per triangle.
    pub indices: Vec<u32>,
}

impl Mesh {
    pub fn vertex_count(&self) -> usize {
        self.positions.len()
    }
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }
    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }
    /// Component-wise `(min, max)` of the vertex positions.
    pub fn bounds(&self) -> Option<([f32; 3], [f32; 3])> {
        let first = Vec3::from(*self.positions.first()?);
        let (lo, hi) = self
            .positions
            .iter()
            .fold((first, first), |(lo, hi), &p| (lo.min(p.into()), hi.max(p.into())));
        Some((lo.to_array(), hi.to_array()))
    }
    /// Writes the mesh to `path`, choosing the format by extension.
    pub fn export(&self, path: &Path) -> Result<()> {
        export_mesh(self, path)
    }
}

/// What to mesh and where to put it.
#[derive(Clone, Copy, Debug, Default)]
pub struct MeshOptions<'a> {
    /// Activated density of the surface; `None` means [`default_iso`].
    pub iso: Option<f32>,
    /// Mesh only this object: voxels outside the bitmap count as empty, so
    /// the mesh is closed where the object was cut from its surroundings.
    pub object: Option<&'a Bitmap>,
    /// Maps field-local coordinates to the output space (object placed
    /// elsewhere); `None` is the identity.
    pub transform: Option<Affine3A>,
}

/// The density at which one voxel-length step has opacity 0.5:
/// 1 − exp(−σ δ) = 0.5 ⇒ σ = ln 2 / δ, with δ the mean grid spacing.
pub fn default_iso(geom: &GridGeom) -> f32 {
    let s = geom.spacing();
    std::f32::consts::LN_2 / ((s.x + s.y + s.z) / 3.0)
}

/// Surface of a scalar grid in grid coordinates (grid point `(x, y, z)` at
/// `(x, y, z)`), before it is placed in the world.
#[derive(Clone, Debug, Default)]
pub struct Surface {
    pub positions: Vec<Vec3>,
    /// Gradient of the value in grid units at each vertex (points inwards,
    /// towards larger values).
    pub gradients: Vec<Vec3>,
    pub indices: Vec<u32>,
}

/// Corner offsets of a cube in the table's numbering.
const CORNERS: [[usize; 3]; 8] = [
    [0, 0, 0],
    [1, 0, 0],
    [1, 1, 0],
    [0, 1, 0],
    [0, 0, 1],
    [1, 0, 1],
    [1, 1, 1],
    [0, 1, 1],
];

/// Each cube edge as (offset of its lower end, axis) in the table's numbering.
const EDGES: [([usize; 3], usize); 12] = [
    ([0, 0, 0], 0),
    ([1, 0, 0], 1),
    ([0, 1, 0], 0),
    ([0, 0, 0], 1),
    ([0, 0, 1], 0),
    ([1, 0, 1], 1),
    ([0, 1, 1], 0),
    ([0, 0, 1], 1),
    ([0, 0, 0], 2),
    ([1, 0, 0], 2),
    ([1, 1, 0], 2),
    ([0, 1, 0], 2),
];

/// The grid padded by one empty point on each side.
struct Padded<'a, F> {
    res: [usize; 3],
    /// Padded resolution (`res + 2`).
    pres: [usize; 3],
    inside: Bitmap,
    value: &'a F,
}

impl<F: Fn(usize) -> f32 + Sync> Padded<'_, F> {
    /// Unpadded flat index of padded point `p`, if it is a real grid point.
    #[inline]
    fn real(&self, p: [isize; 3]) -> Option<usize> {
        let [nx, ny, nz] = self.res.map(|n| n as isize);
        let (x, y, z) = (p[0] - 1, p[1] - 1, p[2] - 1);
        (x >= 0 && y >= 0 && z >= 0 && x < nx && y < ny && z < nz).then(|| (x + nx * (y + ny * z)) as usize)
    }
    #[inline]
    fn is_inside(&self, p: [usize; 3]) -> bool {
        self.real(p.map(|v| v as isize)).is_some_and(|i| self.inside.get(i))
    }
    /// Value at a padded point; padding (and beyond) is empty.
    #[inline]
    fn value(&self, p: [isize; 3]) -> f32 {
        self.real(p).map_or(0.0, |i| (self.value)(i))
    }
    /// Central-difference gradient at a padded point, in grid units.
    fn gradient(&self, p: [isize; 3]) -> Vec3 {
        let mut g = [0.0; 3];
        for (a, ga) in g.iter_mut().enumerate() {
            let (mut lo, mut hi) = (p, p);
            lo[a] -= 1;
            hi[a] += 1;
            *ga = 0.5 * (self.value(hi) - self.value(lo));
        }
        Vec3::from(g)
    }
    /// Flat id of the edge along `axis` whose lower end is padded point `p`.
    #[inline]
    fn edge_id(&self, p: [usize; 3], axis: usize) -> usize {
        3 * (p[0] + self.pres[0] * (p[1] + self.pres[1] * p[2])) + axis
    }
    fn edge_of_id(&self, e: usize) -> ([usize; 3], usize) {
        let (axis, p) = (e % 3, e / 3);
        let x = p % self.pres[0];
        let yz = p / self.pres[0];
        ([x, yz % self.pres[1], yz / self.pres[1]], axis)
    }
    /// Does the surface cross edge `e`?
    fn crosses(&self, e: usize) -> bool {
        let (p, axis) = self.edge_of_id(e);
        let mut q = p;
        q[axis] += 1;
        q[axis] < self.pres[axis] && self.is_inside(p) != self.is_inside(q)
    }
    /// Vertex on crossing edge `e`: position (unpadded grid coordinates,
    /// clamped into the grid so that caps lie on the box face) and gradient.
    fn vertex(&self, e: usize, iso: f32) -> (Vec3, Vec3) {
        let (p, axis) = self.edge_of_id(e);
        let pi = p.map(|v| v as isize);
        let mut qi = pi;
        qi[axis] += 1;
        let (s0, s1) = (self.value(pi), self.value(qi));
        let t = ((iso - s0) / (s1 - s0)).clamp(0.0, 1.0);
        let mut pos = Vec3::new(pi[0] as f32, pi[1] as f32, pi[2] as f32) - Vec3::ONE;
        pos[axis] += t;
        let hi = Vec3::new(self.res[0] as f32, self.res[1] as f32, self.res[2] as f32) - Vec3::ONE;
        let pos = pos.clamp(Vec3::ZERO, hi);
        let mut grad = self.gradient(pi).lerp(self.gradient(qi), t);
        if grad.length_squared().is_nan() || grad.length_squared() <= 1e-24 {
            // Flat neighbourhood: the difference along the edge still tells
            // which side is inside.
            grad = Vec3::ZERO;
            grad[axis] = s1 - s0;
        }
        (pos, grad)
    }
    /// Table index of the cube whose lowest corner is padded point `c`.
    #[inline]
    fn cube_index(&self, c: [usize; 3]) -> usize {
        let mut ci = 0;
        for (k, o) in CORNERS.iter().enumerate() {
            if !self.is_inside([c[0] + o[0], c[1] + o[1], c[2] + o[2]]) {
                ci |= 1 << k;
            }
        }
        ci
    }
}

/// Marching cubes over a scalar grid of resolution `res` whose value at flat
/// index `i` (x fastest) is `value(i)`. Points with value > `iso` are inside;
/// the grid is padded with empty points (value 0), so `iso` must be > 0.
pub fn marching_cubes<F>(res: [usize; 3], iso: f32, value: &F) -> Result<Surface>
where
    F: Fn(usize) -> f32 + Sync,
{
    crate::ensure!(
        iso.is_finite() && iso > 0.0,
        "iso level must be a positive finite density, got {iso}"
    );
    crate::ensure!(res.iter().all(|&n| n >= 1), "grid resolution {res:?} is empty");
    let pres = res.map(|n| n + 2);
    let edges_total = pres.iter().try_fold(3usize, |a, &n| a.checked_mul(n));
    crate::ensure!(
        edges_total.is_some_and(|n| n < u32::MAX as usize * 64),
        "grid {res:?} is too large to mesh"
    );
    let grid = Padded {
        res,
        pres,
        inside: Bitmap::from_fn(res, |i| value(i) > iso),
        value,
    };
    // Crossing edges, ranked: edge → vertex index without a hash map.
    let crossing = RankIndex::new(Bitmap::from_fn([3 * pres[0], pres[1], pres[2]], |e| grid.crosses(e)));
    crate::ensure!(
        crossing.count() < u32::MAX as usize,
        "the surface has too many vertices ({}) for 32-bit indices",
        crossing.count()
    );
    let edges: Vec<usize> = crossing.bits().ones().collect();
    let (positions, gradients): (Vec<Vec3>, Vec<Vec3>) = edges.par_iter().map(|&e| grid.vertex(e, iso)).unzip();
    // One task per slab of cubes along z; collecting in order keeps the
    // triangle order independent of scheduling.
    let slabs: Vec<Vec<u32>> = (0..pres[2] - 1)
        .into_par_iter()
        .map(|cz| slab_triangles(&grid, &crossing, cz))
        .collect();
    Ok(Surface {
        positions,
        gradients,
        indices: slabs.concat(),
    })
}

fn slab_triangles<F: Fn(usize) -> f32 + Sync>(grid: &Padded<F>, crossing: &RankIndex, cz: usize) -> Vec<u32> {
    let mut out = Vec::new();
    for cy in 0..grid.pres[1] - 1 {
        for cx in 0..grid.pres[0] - 1 {
            let c = [cx, cy, cz];
            let ci = grid.cube_index(c);
            if ci == 0 || ci == 255 {
                continue;
            }
            for &edge in TRI_TABLE[ci].iter().take_while(|&&e| e >= 0) {
                let (o, axis) = EDGES[edge as usize];
                let id = grid.edge_id([c[0] + o[0], c[1] + o[1], c[2] + o[2]], axis);
                // The table only names edges whose ends differ, which are
                // exactly the ranked crossing edges.
                let v = crossing.slot(id).expect("table edge is a crossing edge");
                out.push(v as u32);
            }
        }
    }
    out
}

/// Meshes the surface of `field` (or of one object in it) where the
/// activated density crosses the iso level, with outward normals from the
/// density gradient and colours seen from outside (along −normal).
pub fn field_mesh(field: &Field, opts: &MeshOptions) -> Result<Mesh> {
    let geom = field.geom();
    if let Some(b) = opts.object {
        crate::ensure!(
            b.res() == geom.res,
            "object bitmap has resolution {:?} but the field's density grid is {:?}",
            b.res(),
            geom.res
        );
    }
    let iso = opts.iso.unwrap_or_else(|| default_iso(&geom));
    let density = &field.density;
    let value = |i: usize| match opts.object {
        Some(b) if !b.get(i) => 0.0,
        _ => density.sigma_at(i),
    };
    let surface = marching_cubes(geom.res, iso, &value)?;
    let spacing = geom.spacing();
    let local: Vec<Vec3> = surface
        .positions
        .iter()
        .map(|&g| geom.bounds.min + g * spacing)
        .collect();
    // σ grows inwards, so the outward normal is −∇σ (world units).
    let normals: Vec<Vec3> = surface
        .gradients
        .iter()
        .map(|&g| (-(g / spacing)).normalize_or_zero())
        .collect();
    let colors: Vec<[f32; 3]> = local
        .par_iter()
        .zip(&normals)
        .map_init(|| field.sampler(), |s, (&p, &n)| s.color(p, -n).to_array())
        .collect();
    let mut mesh = Mesh {
        positions: local.iter().map(|p| p.to_array()).collect(),
        normals: normals.iter().map(|n| n.to_array()).collect(),
        colors,
        indices: surface.indices,
    };
    if let Some(t) = opts.transform {
        transform_mesh(&mut mesh, &t)?;
    }
    Ok(mesh)
}

/// Applies `t` to positions and normals; a mirroring `t` also flips the
/// winding so that triangles still face outwards.
pub fn transform_mesh(mesh: &mut Mesh, t: &Affine3A) -> Result<()> {
    let det = t.matrix3.determinant();
    crate::ensure!(
        crate::util::invertible(t),
        "mesh transform is singular (determinant {det})"
    );
    let normal_matrix = t.matrix3.inverse().transpose();
    for p in &mut mesh.positions {
        *p = t.transform_point3(Vec3::from(*p)).to_array();
    }
    for n in &mut mesh.normals {
        *n = (normal_matrix * Vec3::from(*n)).normalize_or_zero().to_array();
    }
    if det < 0.0 {
        for tri in mesh.indices.chunks_exact_mut(3) {
            tri.swap(1, 2);
        }
    }
    Ok(())
}

// ------------------------------------------------------------------ writers

/// Writes `mesh` as binary PLY (`.ply`) or binary glTF (`.glb`), chosen by
/// the extension (case-insensitive), atomically.
pub fn export_mesh(mesh: &Mesh, path: &Path) -> Result<()> {
    let bytes = match MeshFormat::of(path)? {
        MeshFormat::Ply => ply_bytes(mesh)?,
        MeshFormat::Glb => glb_bytes(mesh)?,
    };
    crate::error::write_atomic(path, &bytes)
}

/// The mesh file formats we write.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MeshFormat {
    Ply,
    Glb,
}

impl MeshFormat {
    /// The format a path's extension names.
    pub fn of(path: &Path) -> Result<MeshFormat> {
        match crate::util::extension(path).as_str() {
            "ply" => Ok(MeshFormat::Ply),
            "glb" => Ok(MeshFormat::Glb),
            _ => Err(Error::invalid(format!(
                "{}: unknown mesh format; use a .ply or .glb extension",
                path.display()
            ))),
        }
    }
}

fn check_mesh(mesh: &Mesh) -> Result<()> {
    let n = mesh.positions.len();
    crate::ensure!(
        mesh.normals.len() == n && mesh.colors.len() == n,
        "mesh has {n} positions but {} normals and {} colours",
        mesh.normals.len(),
        mesh.colors.len()
    );
    crate::ensure!(
        !mesh.indices.is_empty(),
        "mesh is empty (no surface at this iso level); nothing to export"
    );
    crate::ensure!(
        mesh.indices.len().is_multiple_of(3),
        "mesh has {} indices, not a multiple of 3",
        mesh.indices.len()
    );
    crate::ensure!(
        mesh.indices.iter().all(|&i| (i as usize) < n),
        "mesh index out of range ({n} vertices)"
    );
    Ok(())
}

/// Colour channel in [0, 1] as a byte.
fn to_u8(c: f32) -> u8 {
    (c.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// Binary little-endian PLY: float position and normal, uchar colour per
/// vertex; faces as `uchar count, uint indices`.
pub fn ply_bytes(mesh: &Mesh) -> Result<Vec<u8>> {
    check_mesh(mesh)?;
    let header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment written by isrf\n\
         element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         property float nx\nproperty float ny\nproperty float nz\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\n\
         element face {}\nproperty list uchar uint vertex_indices\nend_header\n",
        mesh.vertex_count(),
        mesh.triangle_count()
    );
    let mut out = Vec::with_capacity(header.len() + 27 * mesh.vertex_count() + 13 * mesh.triangle_count());
    out.extend_from_slice(header.as_bytes());
    for ((p, n), c) in mesh.positions.iter().zip(&mesh.normals).zip(&mesh.colors) {
        for v in p.iter().chain(n) {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend(c.iter().map(|&v| to_u8(v)));
    }
    for tri in mesh.indices.chunks_exact(3) {
        out.push(3);
        for i in tri {
            out.extend_from_slice(&i.to_le_bytes());
        }
    }
    Ok(out)
}

/// Binary glTF 2.0: one mesh with one triangle primitive; POSITION (with
/// min/max), NORMAL and COLOR_0 as float vec3, u32 indices.
pub fn glb_bytes(mesh: &Mesh) -> Result<Vec<u8>> {
    use gltf_json as json;
    use json::validation::{Checked::Valid, USize64};
    check_mesh(mesh)?;
    let n = mesh.vertex_count();
    let mut bin: Vec<u8> = Vec::new();
    let mut views = Vec::new();
    for part in [&mesh.positions, &mesh.normals, &mesh.colors] {
        views.push((bin.len(), 12 * n, json::buffer::Target::ArrayBuffer));
        bin.extend_from_slice(bytemuck::cast_slice(part));
    }
    views.push((
        bin.len(),
        4 * mesh.indices.len(),
        json::buffer::Target::ElementArrayBuffer,
    ));
    bin.extend_from_slice(bytemuck::cast_slice(&mesh.indices));
    crate::ensure!(
        bin.len() < (u32::MAX as usize) - (1 << 20),
        "mesh is too large for a .glb file ({} bytes of data)",
        bin.len()
    );

    let mut root = json::Root::default();
    let buffer = root.push(json::Buffer {
        byte_length: USize64::from(bin.len()),
        extensions: Default::default(),
        extras: Default::default(),
        name: None,
        uri: None,
    });
    let views: Vec<_> = views
        .into_iter()
        .map(|(offset, len, target)| {
            root.push(json::buffer::View {
                buffer,
                byte_length: USize64::from(len),
                byte_offset: Some(USize64::from(offset)),
                byte_stride: None,
                extensions: Default::default(),
                extras: Default::default(),
                name: None,
                target: Some(Valid(target)),
            })
        })
        .collect();
    let (lo, hi) = mesh.bounds().expect("checked non-empty");
    let mut accessor = |view, count: usize, ty, comp, minmax: Option<([f32; 3], [f32; 3])>| {
        root.push(json::Accessor {
            buffer_view: Some(view),
            byte_offset: None,
            count: USize64::from(count),
            component_type: Valid(json::accessor::GenericComponentType(comp)),
            extensions: Default::default(),
            extras: Default::default(),
            type_: Valid(ty),
            min: minmax.map(|(lo, _)| json::Value::from(lo.to_vec())),
            max: minmax.map(|(_, hi)| json::Value::from(hi.to_vec())),
            name: None,
            normalized: false,
            sparse: None,
        })
    };
    use json::accessor::{ComponentType as C, Type as T};
    let pos = accessor(views[0], n, T::Vec3, C::F32, Some((lo, hi)));
    let nor = accessor(views[1], n, T::Vec3, C::F32, None);
    let col = accessor(views[2], n, T::Vec3, C::F32, None);
    let idx = accessor(views[3], mesh.indices.len(), T::Scalar, C::U32, None);
    let primitive = json::mesh::Primitive {
        attributes: [
            (Valid(json::mesh::Semantic::Positions), pos),
            (Valid(json::mesh::Semantic::Normals), nor),
            (Valid(json::mesh::Semantic::Colors(0)), col),
        ]
        .into_iter()
        .collect(),
        extensions: Default::default(),
        extras: Default::default(),
        indices: Some(idx),
        material: None,
        mode: Valid(json::mesh::Mode::Triangles),
        targets: None,
    };
    let mesh_ix = root.push(json::Mesh {
        extensions: Default::default(),
        extras: Default::default(),
        name: None,
        primitives: vec![primitive],
        weights: None,
    });
    let node = root.push(json::Node {
        mesh: Some(mesh_ix),
        ..Default::default()
    });
    let scene = root.push(json::Scene {
        extensions: Default::default(),
        extras: Default::default(),
        name: None,
        nodes: vec![node],
    });
    root.scene = Some(scene);
    root.asset.generator = Some(format!("isrf {}", env!("CARGO_PKG_VERSION")));

    let json_bytes =
        json::serialize::to_vec(&root).map_err(|e| Error::invalid(format!("cannot serialise glTF JSON: {e}")))?;
    let length = 12 + 8 + json_bytes.len().next_multiple_of(4) + 8 + bin.len().next_multiple_of(4);
    let glb = gltf::binary::Glb {
        header: gltf::binary::Header {
            magic: *b"glTF",
            version: 2,
            length: length as u32,
        },
        json: json_bytes.into(),
        bin: Some(bin.into()),
    };
    let mut out = Vec::with_capacity(length);
    glb.to_writer(&mut out)
        .map_err(|e| Error::invalid(format!("cannot write glTF binary: {e}")))?;
    Ok(out)
}
