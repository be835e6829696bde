//! Mesh export (marching cubes, PLY, glTF) and cropped object fields.

use glam::{Affine3A, Quat, Vec3};
use half::f16;
use isrf::edit::crop::{self, object_field};
use isrf::edit::mesh::{default_iso, export_mesh, field_mesh, glb_bytes, marching_cubes, ply_bytes, Mesh, MeshOptions};
use isrf::field::{
    Aabb, Activation, Appearance, Bitmap, ChannelGrid, DensityGrid, Features, Field, GridGeom, Linear, Mlp, RankIndex,
    VmGrid,
};
use std::collections::HashMap;
use std::sync::Arc;

// ------------------------------------------------------------------ helpers

fn cube_geom(n: usize) -> GridGeom {
    GridGeom::new(Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0)), [n; 3])
}

/// Linear ramp of density crossing the default iso level at radius `r`.
fn sphere_raw(g: &GridGeom, r: f32) -> Vec<f32> {
    let iso = default_iso(g);
    let h = g.spacing().x;
    (0..g.len())
        .map(|i| (iso * (1.0 + (r - g.point_of(i).length()) / h)).max(0.0))
        .collect()
}

fn constant_rgb(g: GridGeom, c: [f32; 3]) -> ChannelGrid {
    let data = (0..g.len()).flat_map(|_| c.map(f16::from_f32)).collect();
    ChannelGrid::dense(g, 3, data)
}

const COLOR: [f32; 3] = [0.25, 0.5, 0.75];

fn sphere_field(n: usize, r: f32) -> Field {
    let g = cube_geom(n);
    let density = DensityGrid {
        geom: g,
        raw: sphere_raw(&g, r),
        activation: Activation::Relu,
    };
    Field::new(density, Appearance::Rgb(constant_rgb(g, COLOR)), None, None)
}

/// Small deterministic generator (no extra dev-dependency).
struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 40) as f32) / (1u64 << 24) as f32
    }
    fn point_in(&mut self, b: &Aabb) -> Vec3 {
        b.min + Vec3::new(self.next(), self.next(), self.next()) * b.size()
    }
}

/// Checks that triangles form closed, consistently oriented surfaces: every
/// directed edge occurs once and its reverse once (so every undirected edge
/// is in exactly two triangles). Returns (Euler characteristic, components).
fn check_closed(indices: &[u32], vertex_count: usize) -> (i64, usize) {
    assert!(indices.len().is_multiple_of(3));
    let mut directed: HashMap<(u32, u32), usize> = HashMap::new();
    let mut used = vec![false; vertex_count];
    for t in indices.chunks_exact(3) {
        assert!(
            t[0] != t[1] && t[1] != t[2] && t[0] != t[2],
            "degenerate triangle {t:?}"
        );
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            used[a as usize] = true;
            *directed.entry((a, b)).or_default() += 1;
        }
    }
    for (&(a, b), &n) in &directed {
        assert_eq!(n, 1, "directed edge {a}->{b} used {n} times (non-manifold or flipped)");
        assert_eq!(directed.get(&(b, a)), Some(&1), "edge {a}-{b} is on a boundary");
    }
    assert!(used.iter().all(|&u| u), "unreferenced vertices");
    // Components by union-find over triangle edges.
    let mut parent: Vec<usize> = (0..vertex_count).collect();
    fn find(p: &mut [usize], mut i: usize) -> usize {
        while p[i] != i {
            p[i] = p[p[i]];
            i = p[i];
        }
        i
    }
    for &(a, b) in directed.keys() {
        let (ra, rb) = (find(&mut parent, a as usize), find(&mut parent, b as usize));
        parent[ra] = rb;
    }
    let comps = (0..vertex_count).filter(|&i| find(&mut parent, i) == i).count();
    let (v, e, f) = (vertex_count as i64, directed.len() as i64 / 2, indices.len() as i64 / 3);
    (v - e + f, comps)
}

fn signed_volume(m: &Mesh) -> f32 {
    m.indices
        .chunks_exact(3)
        .map(|t| {
            let [a, b, c] = [0, 1, 2].map(|k| Vec3::from(m.positions[t[k] as usize]));
            a.dot(b.cross(c)) / 6.0
        })
        .sum()
}

// ------------------------------------------------------------ marching cubes

#[test]
fn every_cube_case_gives_a_closed_surface() {
    // The 8 points of a 2³ grid are the 8 corners of one cube; the padding
    // around it makes every case's surface closed.
    for case in 0u32..256 {
        let value = |i: usize| if case >> i & 1 == 1 { 1.0 } else { 0.0 };
        let s = marching_cubes([2, 2, 2], 0.5, &value).unwrap();
        if case == 0 {
            assert!(s.indices.is_empty());
            continue;
        }
        let (chi, comps) = check_closed(&s.indices, s.positions.len());
        assert_eq!(chi, 2 * comps as i64, "case {case:#010b}: not a union of spheres");
        let m = Mesh {
            positions: s.positions.iter().map(|p| p.to_array()).collect(),
            indices: s.indices.clone(),
            ..Default::default()
        };
        assert!(signed_volume(&m) > 0.0, "case {case:#010b}: inward winding");
    }
}

#[test]
fn random_fields_give_closed_oriented_surfaces() {
    let mut rng = Lcg(7);
    for _ in 0..20 {
        let vals: Vec<f32> = (0..7 * 6 * 5).map(|_| rng.next()).collect();
        let s = marching_cubes([7, 6, 5], 0.5, &|i| vals[i]).unwrap();
        check_closed(&s.indices, s.positions.len());
        // Every vertex lies on the grid (caps are clamped onto the box).
        assert!(s
            .positions
            .iter()
            .all(|p| p.cmpge(Vec3::ZERO).all() && p.cmple(Vec3::new(6.0, 5.0, 4.0)).all()));
    }
}

#[test]
fn sphere_mesh_is_watertight_and_accurate() {
    let (n, r) = (40, 0.6);
    let field = sphere_field(n, r);
    let h = field.geom().spacing().x;
    let m = field_mesh(&field, &MeshOptions::default()).unwrap();
    assert!(m.triangle_count() > 1000);
    let (chi, comps) = check_closed(&m.indices, m.vertex_count());
    assert_eq!((chi, comps), (2, 1));
    let (lo, hi) = m.bounds().unwrap();
    for a in 0..3 {
        assert!((lo[a] + r).abs() < h && (hi[a] - r).abs() < h, "bounds {lo:?} {hi:?}");
    }
    for (p, nrm) in m.positions.iter().zip(&m.normals) {
        let p = Vec3::from(*p);
        assert!((p.length() - r).abs() < h, "vertex {p} off the sphere");
        assert!(Vec3::from(*nrm).dot(p.normalize()) > 0.95, "normal not outward at {p}");
    }
    for c in &m.colors {
        for k in 0..3 {
            assert!((c[k] - COLOR[k]).abs() < 1e-3, "colour {c:?}");
        }
    }
    let vol = signed_volume(&m);
    let exact = 4.0 / 3.0 * std::f32::consts::PI * r.powi(3);
    assert!((vol - exact).abs() < 0.03 * exact, "volume {vol} vs {exact}");
    // Deterministic despite the parallel slabs.
    assert_eq!(m, field_mesh(&field, &MeshOptions::default()).unwrap());
}

#[test]
fn bitmap_cut_gives_a_closed_half_sphere() {
    let (n, r) = (40, 0.6);
    let field = sphere_field(n, r);
    let g = field.geom();
    let h = g.spacing().x;
    let half = Bitmap::from_fn(g.res, |i| g.coords(i)[0] < n / 2);
    let cut_x = g.point(n / 2 - 1, 0, 0).x;
    let m = field_mesh(
        &field,
        &MeshOptions {
            object: Some(&half),
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(check_closed(&m.indices, m.vertex_count()), (2, 1));
    let (lo, hi) = m.bounds().unwrap();
    assert!((lo[0] + r).abs() < h);
    // The cap sits between the last kept grid plane and the next one.
    assert!(hi[0] >= cut_x - 1e-5 && hi[0] <= cut_x + h, "cut at {}", hi[0]);
    assert!(m.positions.iter().all(|p| Vec3::from(*p).length() < r + h));
    // Cap normals (away from the rim) point along +x.
    let cap: Vec<_> = m
        .normals
        .iter()
        .zip(&m.positions)
        .filter(|(_, p)| p[0] > cut_x && p[1].hypot(p[2]) < 0.7 * r)
        .collect();
    assert!(!cap.is_empty());
    assert!(cap.iter().all(|(n, _)| n[0] > 0.9), "cap normals");
    let vol = signed_volume(&m);
    let full = 4.0 / 3.0 * std::f32::consts::PI * r.powi(3);
    assert!(vol > 0.4 * full && vol < 0.6 * full, "half volume {vol}");
}

#[test]
fn surface_touching_the_box_is_capped_on_its_faces() {
    let g = cube_geom(16);
    let iso = default_iso(&g);
    let density = DensityGrid {
        geom: g,
        raw: vec![10.0 * iso; g.len()],
        activation: Activation::Relu,
    };
    let field = Field::new(density, Appearance::Rgb(constant_rgb(g, COLOR)), None, None);
    let m = field_mesh(&field, &MeshOptions::default()).unwrap();
    assert_eq!(check_closed(&m.indices, m.vertex_count()), (2, 1));
    assert_eq!(m.bounds().unwrap(), ([-1.0; 3], [1.0; 3]));
    assert!((signed_volume(&m) - 8.0).abs() < 0.05, "{}", signed_volume(&m));
}

#[test]
fn transform_places_the_mesh_and_keeps_winding() {
    let field = sphere_field(24, 0.5);
    let base = field_mesh(&field, &MeshOptions::default()).unwrap();
    let vol = signed_volume(&base);
    let mirror = Affine3A::from_scale(Vec3::new(-1.0, 2.0, 1.0));
    let rigid = Affine3A::from_rotation_translation(Quat::from_rotation_y(0.7), Vec3::new(3.0, -1.0, 0.5));
    for (t, scale) in [(rigid, 1.0), (mirror, 2.0)] {
        let m = field_mesh(
            &field,
            &MeshOptions {
                transform: Some(t),
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(m.vertex_count(), base.vertex_count());
        for (p, q) in m.positions.iter().zip(&base.positions) {
            assert!(Vec3::from(*p).distance(t.transform_point3(Vec3::from(*q))) < 1e-5);
        }
        check_closed(&m.indices, m.vertex_count());
        assert!((signed_volume(&m) - scale * vol).abs() < 1e-3 * scale * vol);
        for (n, p) in m.normals.iter().zip(&m.positions) {
            let centre = t.transform_point3(Vec3::ZERO);
            assert!(Vec3::from(*n).dot(Vec3::from(*p) - centre) > 0.0);
        }
    }
}

#[test]
fn mesh_error_cases() {
    let field = sphere_field(16, 0.5);
    let wrong = Bitmap::new([8, 8, 8]);
    let e = field_mesh(
        &field,
        &MeshOptions {
            object: Some(&wrong),
            ..Default::default()
        },
    )
    .unwrap_err();
    assert!(e.to_string().contains("resolution"), "{e}");
    for iso in [0.0, -1.0, f32::NAN] {
        let opts = MeshOptions {
            iso: Some(iso),
            ..Default::default()
        };
        assert!(field_mesh(&field, &opts).is_err());
    }
    let m = field_mesh(&field, &MeshOptions::default()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    for name in ["mesh.obj", "mesh"] {
        let e = export_mesh(&m, &dir.path().join(name)).unwrap_err();
        assert!(e.to_string().contains("unknown mesh format"), "{e}");
        assert!(!dir.path().join(name).exists());
    }
    // Nothing above an absurd iso level: an empty mesh is not exported.
    let empty = field_mesh(
        &field,
        &MeshOptions {
            iso: Some(1e30),
            ..Default::default()
        },
    )
    .unwrap();
    assert!(empty.is_empty());
    assert!(export_mesh(&empty, &dir.path().join("e.ply")).is_err());
}

// ------------------------------------------------------------------ writers

#[test]
fn glb_reads_back_with_the_gltf_crate() {
    let field = sphere_field(24, 0.5);
    let m = field_mesh(&field, &MeshOptions::default()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sphere.GLB");
    export_mesh(&m, &path).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    assert_eq!(bytes, glb_bytes(&m).unwrap());
    assert_eq!(bytes.len() % 4, 0);
    assert_eq!(
        u32::from_le_bytes(bytes[8..12].try_into().unwrap()) as usize,
        bytes.len()
    );

    let gltf = gltf::Gltf::from_slice(&bytes).expect("valid glb");
    let blob = gltf.blob.clone();
    assert_eq!(gltf.meshes().count(), 1);
    let prim = gltf.meshes().next().unwrap().primitives().next().unwrap();
    assert_eq!(prim.mode(), gltf::mesh::Mode::Triangles);
    let bb = prim.bounding_box();
    let (lo, hi) = m.bounds().unwrap();
    assert_eq!((bb.min, bb.max), (lo, hi));
    let reader = prim.reader(|b| match b.source() {
        gltf::buffer::Source::Bin => blob.as_deref(),
        _ => None,
    });
    let pos: Vec<[f32; 3]> = reader.read_positions().unwrap().collect();
    let nor: Vec<[f32; 3]> = reader.read_normals().unwrap().collect();
    let col: Vec<[f32; 3]> = reader.read_colors(0).unwrap().into_rgb_f32().collect();
    let idx: Vec<u32> = reader.read_indices().unwrap().into_u32().collect();
    assert_eq!(pos, m.positions);
    assert_eq!(nor, m.normals);
    assert_eq!(col, m.colors);
    assert_eq!(idx, m.indices);
}

#[test]
fn ply_header_and_body_are_right() {
    let field = sphere_field(20, 0.5);
    let m = field_mesh(&field, &MeshOptions::default()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sphere.ply");
    export_mesh(&m, &path).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    assert_eq!(bytes, ply_bytes(&m).unwrap());
    let end = b"end_header\n";
    let hlen = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
    let header = std::str::from_utf8(&bytes[..hlen]).unwrap();
    let lines: Vec<&str> = header.lines().collect();
    assert_eq!(lines[0], "ply");
    assert_eq!(lines[1], "format binary_little_endian 1.0");
    let count = |el: &str| -> usize {
        let l = lines.iter().find(|l| l.starts_with(&format!("element {el} "))).unwrap();
        l.rsplit(' ').next().unwrap().parse().unwrap()
    };
    assert_eq!(count("vertex"), m.vertex_count());
    assert_eq!(count("face"), m.triangle_count());
    let props: Vec<&str> = lines.iter().filter(|l| l.starts_with("property")).copied().collect();
    assert_eq!(props.len(), 10);
    assert_eq!(
        props[6..9],
        ["property uchar red", "property uchar green", "property uchar blue"]
    );
    assert_eq!(props[9], "property list uchar uint vertex_indices");
    assert_eq!(bytes.len(), hlen + 27 * m.vertex_count() + 13 * m.triangle_count());
    // Parse the body back.
    let f32_at = |o: usize| f32::from_le_bytes(bytes[o..o + 4].try_into().unwrap());
    for v in 0..m.vertex_count() {
        let o = hlen + 27 * v;
        assert_eq!([f32_at(o), f32_at(o + 4), f32_at(o + 8)], m.positions[v]);
        assert_eq!([f32_at(o + 12), f32_at(o + 16), f32_at(o + 20)], m.normals[v]);
        let rgb = &bytes[o + 24..o + 27];
        for (byte, c) in rgb.iter().zip(m.colors[v]) {
            assert_eq!(*byte, (c * 255.0).round() as u8);
        }
    }
    let faces = hlen + 27 * m.vertex_count();
    for (t, tri) in m.indices.chunks_exact(3).enumerate() {
        let o = faces + 13 * t;
        assert_eq!(bytes[o], 3);
        for k in 0..3 {
            let i = u32::from_le_bytes(bytes[o + 1 + 4 * k..o + 5 + 4 * k].try_into().unwrap());
            assert_eq!(i, tri[k]);
        }
    }
}

// ----------------------------------------------------------------- cropping

/// Dense field: sphere density (given activation), colour and features that
/// encode the world position (so any misalignment shows).
fn position_coded_field(n: usize, activation: Activation, feat_res: usize) -> Field {
    let g = cube_geom(n);
    let mut raw = sphere_raw(&g, 0.6);
    if let Activation::Softplus { shift } = activation {
        // Same σ where the sphere is, tiny σ elsewhere.
        raw.iter_mut().for_each(|r| {
            *r = if *r > 0.0 {
                *r + (-(-*r).exp_m1()).ln() - shift
            } else {
                -15.0 - shift
            }
        });
    }
    let rgb = (0..g.len())
        .flat_map(|i| {
            let p = g.point_of(i);
            [0.5 + 0.5 * p.x, 0.5 + 0.5 * p.y, 0.5 + 0.25 * p.z].map(f16::from_f32)
        })
        .collect();
    let fg = GridGeom::new(g.bounds, [feat_res; 3]);
    let feats = (0..fg.len())
        .flat_map(|i| fg.point_of(i).to_array().map(f16::from_f32))
        .collect();
    Field::new(
        DensityGrid {
            geom: g,
            raw,
            activation,
        },
        Appearance::Rgb(ChannelGrid::dense(g, 3, rgb)),
        Some(Features::Grid(ChannelGrid::dense(fg, 3, feats))),
        None,
    )
}

/// The original field with σ multiplied by the bitmap at grid points.
fn masked(field: &Field, b: &Bitmap) -> DensityGrid {
    let mut d = field.density.clone();
    for (i, r) in d.raw.iter_mut().enumerate() {
        if !b.get(i) {
            *r = crop::empty_raw(d.activation);
        }
    }
    d
}

/// Voxels of the sphere (radius 0.62) with x index below half.
fn half_sphere_bitmap(g: &GridGeom) -> Bitmap {
    Bitmap::from_fn(g.res, |i| {
        g.coords(i)[0] < g.res[0] / 2 && g.point_of(i).length() < 0.62
    })
}

fn assert_close(a: &[f32], b: &[f32], tol: f32, what: &str) {
    for (x, y) in a.iter().zip(b) {
        assert!((x - y).abs() <= tol, "{what}: {a:?} vs {b:?}");
    }
}

#[test]
fn cropped_dense_field_matches_masked_original() {
    for activation in [Activation::Relu, Activation::Softplus { shift: -3.0 }] {
        let field = position_coded_field(32, activation, 21);
        let g = field.geom();
        let b = half_sphere_bitmap(&g);
        let (bmin, bmax) = b.bounding_box().unwrap();
        let c = object_field(&field, &b, 2).unwrap();
        let lo = bmin.map(|v| v - 2);
        let hi = [0, 1, 2].map(|a| (bmax[a] + 2).min(31));
        assert_eq!(c.res(), [0, 1, 2].map(|a| hi[a] - lo[a] + 1));
        assert_eq!(
            c.bounds(),
            Aabb::new(g.point(lo[0], lo[1], lo[2]), g.point(hi[0], hi[1], hi[2]))
        );
        // Grid points: exactly σ·b (and empty outside the object).
        let cg = c.geom();
        for i in 0..cg.len() {
            let [x, y, z] = cg.coords(i);
            let j = g.index(x + lo[0], y + lo[1], z + lo[2]);
            let s = c.density.sigma_at(i);
            if b.get(j) {
                assert_eq!(s, field.density.sigma_at(j));
            } else {
                assert!(s < 1e-8, "σ {s} outside the object");
            }
        }
        // Anywhere in the box: density, colour and features as the original.
        let reference = masked(&field, &b);
        let (mut so, mut sc) = (field.sampler(), c.sampler());
        let (mut fo, mut fc) = ([0.0; 3], [0.0; 3]);
        let mut rng = Lcg(3);
        for _ in 0..2000 {
            let p = rng.point_in(&c.bounds());
            let (a, e) = (c.sigma(p), reference.sigma(p));
            assert!((a - e).abs() <= 1e-4 * e.max(1.0), "σ {a} vs {e} at {p}");
            let d = Vec3::Z;
            assert_close(&sc.color(p, d).to_array(), &so.color(p, d).to_array(), 1e-5, "colour");
            sc.features(p, &mut fc);
            so.features(p, &mut fo);
            assert_close(&fc, &fo, 2e-3, "features");
            assert_close(&fc, &p.to_array(), 3e-3, "features encode position");
        }
    }
}

fn random_vm(rng: &mut Lcg, geom: GridGeom, comps: [usize; 3], out: usize) -> VmGrid {
    let r = geom.res;
    let mut planes: [Vec<f32>; 3] = Default::default();
    let mut lines: [Vec<f32>; 3] = Default::default();
    for (m, &(a, b, c)) in isrf::field::vm::MODE_AXES.iter().enumerate() {
        planes[m] = (0..comps[m] * r[a] * r[b]).map(|_| rng.next() - 0.5).collect();
        lines[m] = (0..comps[m] * r[c]).map(|_| rng.next() - 0.5).collect();
    }
    let total: usize = comps.iter().sum();
    VmGrid {
        geom,
        comps,
        planes,
        lines,
        basis: (0..total * out).map(|_| rng.next() - 0.5).collect(),
        out,
    }
}

#[test]
fn cropped_vm_grids_keep_their_values() {
    let mut rng = Lcg(11);
    let g = cube_geom(33);
    // Appearance VM on a grid that does not line up with the density grid,
    // features VM on the density's own grid.
    let app = random_vm(&mut rng, GridGeom::new(g.bounds, [20, 14, 26]), [2, 3, 2], 5);
    let feat = random_vm(&mut rng, g, [3, 2, 4], 6);
    let inputs = 5 + 3;
    let mlp = Mlp {
        feat_pe: 0,
        view_pe: 0,
        layers: vec![Linear {
            inputs,
            outputs: 3,
            weight: (0..3 * inputs).map(|_| rng.next() - 0.5).collect(),
            bias: vec![0.0; 3],
        }],
    };
    let field = Field::new(
        DensityGrid {
            geom: g,
            raw: sphere_raw(&g, 0.6),
            activation: Activation::Relu,
        },
        Appearance::Vm { grid: app.clone(), mlp },
        Some(Features::Vm(feat.clone())),
        None,
    );
    let b = half_sphere_bitmap(&g);
    let c = object_field(&field, &b, 1).unwrap();
    let (Appearance::Vm { grid: capp, .. }, Some(Features::Vm(cfeat))) = (&c.appearance, &c.features) else {
        panic!("kinds changed");
    };
    assert_eq!(capp.geom.bounds, c.bounds());
    // Features: same grid as the density, cut exactly.
    assert_eq!(cfeat.geom.res, c.res());
    let (mut s0, mut s1) = (vec![0.0; 9], vec![0.0; 9]);
    let (mut o0, mut o1) = (vec![0.0; 6], vec![0.0; 6]);
    let mut sb = c.sampler();
    let mut rng = Lcg(5);
    for _ in 0..1000 {
        let p = rng.point_in(&c.bounds());
        feat.sample(p, &mut s0, &mut o0);
        cfeat.sample(p, &mut s1, &mut o1);
        assert_close(&o1, &o0, 1e-5, "vm features");
        let mut f = [0.0; 6];
        sb.features(p, &mut f);
        assert_close(&f, &o0, 1e-5, "sampler features");
    }
    // Appearance: resampled; exact at its own grid points, at no coarser spacing.
    let sp = app.geom.spacing();
    let csp = capp.geom.spacing();
    assert!(csp.cmple(sp * 1.0001).all(), "{csp} coarser than {sp}");
    let (mut o0, mut o1) = (vec![0.0; 5], vec![0.0; 5]);
    for i in 0..capp.geom.len() {
        let p = capp.geom.point_of(i);
        app.sample(p, &mut s0, &mut o0);
        capp.sample(p, &mut s1, &mut o1);
        assert_close(&o1, &o0, 1e-5, "vm appearance at grid points");
    }
}

/// Sphere field with sparse appearance and features over its occupied voxels.
fn sparse_field() -> Field {
    let g = cube_geom(28);
    let raw = sphere_raw(&g, 0.6);
    let occ = Arc::new(RankIndex::new(Bitmap::from_fn(g.res, |i| raw[i] > 0.0)));
    let mut rng = Lcg(9);
    let rgb = (0..occ.count() * 3).map(|_| f16::from_f32(rng.next())).collect();
    let feats = (0..occ.count() * 4).map(|_| f16::from_f32(rng.next() - 0.5)).collect();
    Field::new(
        DensityGrid {
            geom: g,
            raw,
            activation: Activation::Relu,
        },
        Appearance::Rgb(ChannelGrid::sparse(g, 3, occ.clone(), rgb)),
        Some(Features::Grid(ChannelGrid::sparse(g, 4, occ.clone(), feats))),
        Some(occ),
    )
}

#[test]
fn cropped_sparse_field_keeps_renormalised_samples() {
    let field = sparse_field();
    let g = field.geom();
    let b = half_sphere_bitmap(&g);
    let c = object_field(&field, &b, 2).unwrap();
    let occ = c.occupancy.as_ref().expect("sparse field keeps an occupancy");
    let Appearance::Rgb(rgb) = &c.appearance else { panic!() };
    let isrf::field::Layout::Sparse(ix) = &rgb.layout else {
        panic!("appearance should stay sparse")
    };
    assert!(Arc::ptr_eq(ix, occ));
    assert_eq!(rgb.slots(), occ.count());
    assert!(occ.count() < field.occupancy.as_ref().unwrap().count());
    // Save and load: a valid standalone field file.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("object.safetensors");
    c.save(&path).unwrap();
    let loaded = Field::load(&path).unwrap();
    assert_eq!(loaded.bounds(), c.bounds());
    let reference = masked(&field, &b);
    let (mut so, mut sc, mut sl) = (field.sampler(), c.sampler(), loaded.sampler());
    let mut f = [[0.0; 4]; 3];
    let mut rng = Lcg(4);
    let mut checked = 0;
    for _ in 0..3000 {
        let p = rng.point_in(&c.bounds());
        assert!((c.sigma(p) - reference.sigma(p)).abs() <= 1e-4 * reference.sigma(p).max(1.0));
        let co = so.color(p, Vec3::Y).to_array();
        assert_close(&sc.color(p, Vec3::Y).to_array(), &co, 1e-5, "sparse colour");
        assert_close(&sl.color(p, Vec3::Y).to_array(), &co, 1e-5, "loaded colour");
        so.features(p, &mut f[0]);
        sc.features(p, &mut f[1]);
        sl.features(p, &mut f[2]);
        assert_close(&f[1], &f[0], 1e-5, "sparse features");
        // Files keep features in 8 bits: within half a step of the
        // channel's range (|f| ≤ 0.5 here, so 0.5 / 254), plus f16 rounding.
        assert_close(&f[2], &f[0], 0.5 / 254.0 + 1e-4, "loaded features");
        checked += (f[0] != [0.0; 4]) as usize;
    }
    assert!(checked > 500, "too few points hit stored voxels: {checked}");
}

#[test]
fn crop_error_cases() {
    let field = sphere_field(16, 0.5);
    let e = object_field(&field, &Bitmap::new([16, 16, 16]), 1).unwrap_err();
    assert!(e.to_string().contains("empty"), "{e}");
    let mut wrong = Bitmap::new([16, 16, 8]);
    wrong.set(5, true);
    let e = object_field(&field, &wrong, 1).unwrap_err();
    assert!(e.to_string().contains("resolution"), "{e}");
    // A single voxel at the far corner still gives a valid (2³) field.
    let mut one = Bitmap::new([16; 3]);
    one.set(16 * 16 * 16 - 1, true);
    let c = object_field(&field, &one, 0).unwrap();
    assert_eq!(c.res(), [2, 2, 2]);
    assert_eq!(c.bounds().max, Vec3::ONE);
}

// --------------------------------------------------------------- measurement

/// Prints the marching-cubes time and triangle count at 128³ (run with
/// `--nocapture`); asserts only that the mesh is closed.
#[test]
fn measure_marching_cubes_128() {
    let t0 = std::time::Instant::now();
    let field = sphere_field(128, 0.7);
    let build = t0.elapsed();
    let t1 = std::time::Instant::now();
    let m = field_mesh(&field, &MeshOptions::default()).unwrap();
    let mc = t1.elapsed();
    println!(
        "marching cubes 128³ sphere: {:.1} ms, {} triangles, {} vertices (field built in {:.1} ms, {} threads)",
        mc.as_secs_f64() * 1e3,
        m.triangle_count(),
        m.vertex_count(),
        build.as_secs_f64() * 1e3,
        rayon::current_num_threads()
    );
    assert_eq!(check_closed(&m.indices, m.vertex_count()), (2, 1));
}
