//! The editing session: fields and objects with their placements, the
//! segmentation parameters, undo/redo and the edit log. `apply` is the one
//! entry point for every [`Command`].

use super::{CameraSource, Command, Export, FieldSource, StrokeSource, TransformSpec};
use crate::camera::{Camera, CameraSet};
use crate::demo::{DemoObject, STROKE_RADIUS};
use crate::edit::compose::{compose, object_center, FieldPlacement, ObjectPlacement};
use crate::error::{Error, Result};
use crate::field::{Bitmap, Field};
use crate::render::{render, save_png, to_rgb8, ColorEdit, Layer, Probe, RenderOptions, Scene};
use crate::segment::{
    load_strokes_in, mask_bound, scribble_stroke, Grower, Growth, MaskBuilder, Polarity, SegmentParams, Stroke,
    Timings, MAX_GROW_STEPS,
};
use crate::util::Progress;
use crate::{ensure, Result as R};
use glam::{Affine3A, Vec2, Vec3};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// What a demo field brings besides its grids: cameras and built-in strokes.
#[derive(Debug)]
pub struct DemoInfo {
    pub cameras: CameraSet,
    pub eval_cameras: CameraSet,
    pub stroke_camera: Camera,
    pub objects: Vec<DemoObject>,
}

#[derive(Clone, Debug)]
pub struct FieldEntry {
    pub name: String,
    pub source: FieldSource,
    pub field: Arc<Field>,
    pub transform: Affine3A,
    pub visible: bool,
    pub demo: Option<Arc<DemoInfo>>,
}

#[derive(Clone, Debug)]
pub struct ObjectEntry {
    pub name: String,
    /// Name of the field it was cut from.
    pub field: String,
    pub mask: Arc<Bitmap>,
    pub transform: Affine3A,
    pub removed: bool,
    pub visible: bool,
    pub duplicate: bool,
    pub color_edit: Option<ColorEdit>,
}

/// Everything undo/redo restores. Cloning shares grids and bitmaps.
#[derive(Clone, Debug, Default)]
pub struct State {
    pub fields: Vec<FieldEntry>,
    pub objects: Vec<ObjectEntry>,
    pub params: SegmentParams,
    pub background: [f32; 3],
}

/// Draws colour frames for `Render` commands in place of the CPU reference
/// renderer (the editor's GPU ray marcher implements it for `isrf run --gpu`).
pub trait FrameRenderer {
    /// Colours in [0, 1], row-major, `camera`'s size.
    fn render_rgb(&mut self, scene: Arc<Scene>, camera: &Camera) -> Result<Vec<Vec3>>;
}

/// What one command produced.
#[derive(Clone, Debug, Default)]
pub struct StepOutput {
    pub files: Vec<PathBuf>,
    pub message: String,
    pub timings: Option<Timings>,
}

#[derive(Debug)]
pub struct Session {
    pub state: State,
    undo: Vec<(State, Command)>,
    redo: Vec<(State, Command)>,
    /// Relative input paths (fields, strokes, cameras) resolve against this.
    pub base_dir: PathBuf,
    /// Relative output paths (renders, exports) resolve against this.
    pub out_dir: PathBuf,
    /// What the command being applied has done so far (frames rendered,
    /// strokes segmented, growth steps); cleared when it returns.
    pub progress: Progress,
}

impl Default for Session {
    fn default() -> Self {
        Session::new(".", ".")
    }
}

impl Session {
    pub fn new(base_dir: impl Into<PathBuf>, out_dir: impl Into<PathBuf>) -> Self {
        Session {
            state: State {
                background: [1.0; 3],
                ..Default::default()
            },
            undo: vec![],
            redo: vec![],
            base_dir: base_dir.into(),
            out_dir: out_dir.into(),
            progress: Progress::default(),
        }
    }

    /// The edits applied so far, oldest first (undone ones excluded).
    pub fn log(&self) -> Vec<Command> {
        self.undo.iter().map(|(_, c)| c.clone()).collect()
    }
    pub fn can_undo(&self) -> bool {
        !self.undo.is_empty()
    }
    pub fn can_redo(&self) -> bool {
        !self.redo.is_empty()
    }
    /// Undoes the last edit; returns it.
    pub fn undo(&mut self) -> Option<Command> {
        let (prev, cmd) = self.undo.pop()?;
        let cur = std::mem::replace(&mut self.state, prev);
        self.redo.push((cur, cmd.clone()));
        Some(cmd)
    }
    pub fn redo(&mut self) -> Option<Command> {
        let (next, cmd) = self.redo.pop()?;
        let cur = std::mem::replace(&mut self.state, next);
        self.undo.push((cur, cmd.clone()));
        Some(cmd)
    }

    /// Validates and performs a command. Edits go on the undo stack; render
    /// and export commands only write files. On error nothing changes.
    pub fn apply(&mut self, cmd: &Command) -> Result<StepOutput> {
        self.apply_with(cmd, None)
    }

    /// [`Session::apply`], with colour frames of `Render` commands drawn by
    /// `renderer` (e.g. the GPU ray marcher) instead of the CPU renderer.
    pub fn apply_with(&mut self, cmd: &Command, renderer: Option<&mut dyn FrameRenderer>) -> Result<StepOutput> {
        let out = self.apply_inner(cmd, renderer);
        self.progress.clear();
        out
    }

    fn apply_inner(&mut self, cmd: &Command, renderer: Option<&mut dyn FrameRenderer>) -> Result<StepOutput> {
        if !cmd.is_edit() {
            return self.output(cmd, renderer);
        }
        let mut next = self.state.clone();
        let out = self.edit(&mut next, cmd)?;
        let prev = std::mem::replace(&mut self.state, next);
        self.undo.push((prev, cmd.clone()));
        self.redo.clear();
        Ok(out)
    }

    // ---------------------------------------------------------------- lookups

    pub fn field(&self, name: &str) -> Result<&FieldEntry> {
        find_field(&self.state, name)
    }
    pub fn object(&self, name: &str) -> Result<&ObjectEntry> {
        find_object(&self.state, name)
    }
    fn resolve(&self, p: &Path) -> PathBuf {
        if p.is_absolute() {
            p.to_path_buf()
        } else {
            self.base_dir.join(p)
        }
    }
    fn output_path(&self, p: &Path) -> PathBuf {
        if p.is_absolute() {
            p.to_path_buf()
        } else {
            self.out_dir.join(p)
        }
    }

    /// The composition as a renderable scene, and for each object the layer
    /// that shows it (its own layer, or its field's).
    pub fn scene(&self) -> Scene {
        scene_of(&self.state).0
    }

    // ------------------------------------------------------------------ edits

    fn edit(&self, st: &mut State, cmd: &Command) -> Result<StepOutput> {
        let mut out = StepOutput::default();
        match cmd {
            Command::LoadField {
                name,
                source,
                transform,
            } => {
                check_new_name(st, name)?;
                self.progress.set(&format!("loading '{name}'"), 0, 0);
                let (field, demo) = self.load_source(source)?;
                let pivot = field.bounds().center();
                let t = match transform {
                    Some(t) => {
                        t.validate()?;
                        t.affine(pivot)
                    }
                    None => Affine3A::IDENTITY,
                };
                out.message = format!("loaded '{name}' ({:?} grid)", field.res());
                st.fields.push(FieldEntry {
                    name: name.clone(),
                    source: source.clone(),
                    field,
                    transform: t,
                    visible: true,
                    demo,
                });
            }
            Command::TransformField { field, transform } => {
                transform.validate()?;
                let f = find_field_mut(st, field)?;
                let pivot = f.transform.transform_point3(f.field.bounds().center());
                f.transform = transform.affine(pivot) * f.transform;
            }
            Command::SetParams { .. } => st.params = cmd.merged_params(&st.params)?,
            Command::Stroke {
                object,
                field,
                polarity,
                source,
            } => {
                out = self.stroke(st, object, field.as_deref(), *polarity, source)?;
            }
            Command::Grow { object, steps } => {
                let o = find_object(st, object)?.clone();
                let f = find_field(st, &o.field)?;
                let cache = f.field.feature_cache()?;
                let mut mask = (*o.mask).clone();
                let mut g = Grower::new(&cache, st.params.grow);
                if let Some(b) = mask_bound(&cache, &mask, &st.params) {
                    g = g.with_bound(b);
                }
                let total = match steps {
                    Growth::Steps(n) => *n as u64,
                    Growth::Converge => 0,
                };
                let label = format!("growing '{object}'");
                let n = g.grow(&mut mask, *steps, MAX_GROW_STEPS, |i| {
                    self.progress.set(&label, i as u64, total)
                });
                out.message = format!("'{object}': {} -> {} voxels in {n} steps", o.mask.count(), mask.count());
                find_object_mut(st, object)?.mask = Arc::new(mask);
            }
            Command::Remove { object } => find_object_mut(st, object)?.removed = true,
            Command::Restore { object } => find_object_mut(st, object)?.removed = false,
            Command::SetVisible { target, visible } => {
                if let Ok(f) = find_field_mut(st, target) {
                    f.visible = *visible;
                } else {
                    find_object_mut(st, target)?.visible = *visible;
                }
            }
            Command::Transform { object, transform } => {
                transform.validate()?;
                let pivot = object_pivot(st, object)?;
                let o = find_object_mut(st, object)?;
                o.transform = transform.affine(pivot) * o.transform;
            }
            Command::Duplicate {
                object,
                name,
                transform,
            } => {
                check_new_name(st, name)?;
                let mut copy = find_object(st, object)?.clone();
                if let Some(t) = transform {
                    t.validate()?;
                    copy.transform = t.affine(object_pivot(st, object)?) * copy.transform;
                }
                copy.name = name.clone();
                copy.duplicate = true;
                copy.removed = false;
                st.objects.push(copy);
            }
            Command::Appearance { object, edit } => {
                edit.validate()?;
                find_object_mut(st, object)?.color_edit = (!edit.is_identity()).then_some(*edit);
            }
            Command::Rename { target, name } => {
                check_new_name(st, name)?;
                if let Some(f) = st.fields.iter_mut().find(|f| &f.name == target) {
                    f.name = name.clone();
                    for o in st.objects.iter_mut().filter(|o| &o.field == target) {
                        o.field = name.clone();
                    }
                } else {
                    find_object_mut(st, target)?.name = name.clone();
                }
            }
            Command::Delete { target } => {
                if st.fields.iter().any(|f| &f.name == target) {
                    st.fields.retain(|f| &f.name != target);
                    st.objects.retain(|o| &o.field != target);
                } else {
                    find_object(st, target)?;
                    st.objects.retain(|o| &o.name != target);
                }
            }
            Command::Render { .. } | Command::Export(_) => unreachable!("outputs are not edits"),
        }
        Ok(out)
    }

    fn load_source(&self, source: &FieldSource) -> Result<(Arc<Field>, Option<Arc<DemoInfo>>)> {
        match source {
            FieldSource::File(p) => Ok((Arc::new(Field::load(&self.resolve(p))?), None)),
            FieldSource::Demo { scene, res, seed } => {
                let d = crate::demo::build(scene, *res, *seed)?;
                let info = DemoInfo {
                    cameras: d.cameras,
                    eval_cameras: d.eval_cameras,
                    stroke_camera: d.stroke_camera,
                    objects: d.objects,
                };
                Ok((Arc::new(d.field), Some(Arc::new(info))))
            }
        }
    }

    fn strokes_of(&self, f: &FieldEntry, object: &str, source: &StrokeSource) -> Result<Vec<Stroke>> {
        Ok(match source {
            StrokeSource::Inline(doc) => vec![doc.to_stroke()?],
            // Strokes may name a view (`"camera": {"file_path": "image012"}`)
            // of the capture the field was trained on.
            StrokeSource::File(p) => {
                let cams = match &f.source {
                    FieldSource::File(fp) => crate::camera::set::capture_cameras(&self.resolve(fp)),
                    FieldSource::Demo { .. } => None,
                };
                // The capture's cameras are in the field's frame: follow it.
                load_strokes_in(&self.resolve(p), cams.as_ref(), f.transform)?
            }
            StrokeSource::Scribble { path, camera } => {
                vec![scribble_stroke(
                    &self.resolve(path),
                    camera.to_camera()?,
                    Polarity::Positive,
                    object,
                )?]
            }
            StrokeSource::Demo { object: demo_object } => {
                let info = f.demo.as_ref().ok_or_else(|| {
                    Error::invalid(format!(
                        "field '{}' is not a demo scene: it has no built-in strokes",
                        f.name
                    ))
                })?;
                let o = info.objects.iter().find(|o| &o.name == demo_object).ok_or_else(|| {
                    let names: Vec<&str> = info.objects.iter().map(|o| o.name.as_str()).collect();
                    Error::invalid(format!(
                        "demo '{}' has no object '{demo_object}' (it has: {})",
                        f.name,
                        names.join(", ")
                    ))
                })?;
                let mut px: Vec<Vec2> = o
                    .stroke
                    .iter()
                    .filter_map(|&p| crate::demo::strokes::pixel_of(&info.stroke_camera, p))
                    .map(|p| Vec2::new(p[0] as f32 + 0.5, p[1] as f32 + 0.5))
                    .collect();
                px.dedup();
                // The demo's cameras are in the field's frame: follow the field.
                let mut camera = info.stroke_camera;
                camera.c2w = f.transform * camera.c2w;
                vec![Stroke {
                    camera,
                    points: px,
                    radius: STROKE_RADIUS,
                    polarity: Polarity::Positive,
                    object: object.into(),
                    joined: true,
                }]
            }
        })
    }

    fn stroke(
        &self,
        st: &mut State,
        object: &str,
        field: Option<&str>,
        polarity: Option<Polarity>,
        source: &StrokeSource,
    ) -> Result<StepOutput> {
        let existing = st.objects.iter().find(|o| o.name == object).cloned();
        let field_name = match (&existing, field) {
            (Some(o), Some(f)) if o.field != f => {
                return Err(Error::invalid(format!(
                    "object '{object}' belongs to field '{}', not '{f}'",
                    o.field
                )))
            }
            (Some(o), _) => o.field.clone(),
            (None, Some(f)) => f.to_string(),
            (None, None) => st
                .fields
                .first()
                .map(|f| f.name.clone())
                .ok_or_else(|| Error::invalid("no field is loaded to stroke on"))?,
        };
        if existing.is_none() {
            check_new_name(st, object)?;
        }
        let f = find_field(st, &field_name)?.clone();
        let strokes = self.strokes_of(&f, object, source)?;
        self.progress.set("per-voxel features", 0, 0);
        let cache = f.field.feature_cache()?;
        // Stroke features come from the field as it stands in the world.
        let scene = Scene::new(vec![Layer {
            to_world: f.transform,
            ..Layer::new(f.field.clone())
        }]);
        let mut builder = MaskBuilder::new(
            existing
                .as_ref()
                .map_or_else(|| Bitmap::new(f.field.res()), |o| (*o.mask).clone()),
        );
        let mut total = Timings::default();
        for (i, s) in strokes.iter().enumerate() {
            self.progress
                .set(&format!("segmenting '{object}'"), i as u64, strokes.len() as u64);
            let pol = polarity.unwrap_or(s.polarity);
            if existing.is_none() && pol == Polarity::Negative && !builder.mask.any() {
                return Err(Error::invalid(format!(
                    "a negative stroke needs an existing object: there is no '{object}' yet"
                )));
            }
            total = builder.stroke(&scene, &cache, s, pol, &st.params)?;
        }
        let mask = builder.mask;
        let msg = format!(
            "'{object}': {} voxels (last stroke {:.0} ms)",
            mask.count(),
            total.total_ms()
        );
        match st.objects.iter_mut().find(|o| o.name == object) {
            Some(o) => o.mask = Arc::new(mask),
            None => st.objects.push(ObjectEntry {
                name: object.into(),
                field: field_name,
                mask: Arc::new(mask),
                transform: Affine3A::IDENTITY,
                removed: false,
                visible: true,
                duplicate: false,
                color_edit: None,
            }),
        }
        Ok(StepOutput {
            message: msg,
            timings: Some(total),
            ..Default::default()
        })
    }

    // ---------------------------------------------------------------- outputs

    /// Cameras of a camera source, in world coordinates.
    pub fn cameras(&self, src: &CameraSource) -> Result<CameraSet> {
        src.validate()?;
        match src {
            CameraSource::File(p) => CameraSet::load(&self.resolve(p)),
            CameraSource::Demo { field, eval } => {
                let f = self.field(field)?;
                let info = f
                    .demo
                    .as_ref()
                    .ok_or_else(|| Error::invalid(format!("field '{field}' is not a demo scene: it has no cameras")))?;
                let mut set = if *eval {
                    info.eval_cameras.clone()
                } else {
                    info.cameras.clone()
                };
                for fr in &mut set.frames {
                    fr.camera.c2w = f.transform * fr.camera.c2w;
                }
                Ok(set)
            }
            CameraSource::Orbit { .. } => Ok(src.orbit_set().expect("orbit source")),
        }
    }

    fn output(&self, cmd: &Command, mut renderer: Option<&mut dyn FrameRenderer>) -> Result<StepOutput> {
        let mut out = StepOutput::default();
        match cmd {
            Command::Render {
                cameras,
                out: dir,
                downscale,
                frames,
                depth,
                background,
            } => {
                ensure!(*downscale >= 1, "downscale must be at least 1");
                let mut cams = self.cameras(cameras)?;
                if let Some(n) = frames {
                    cams.frames.truncate(*n);
                }
                let mut scene = self.scene();
                if let Some(b) = background {
                    scene.background = Vec3::from(*b);
                }
                let dir = self.output_path(dir);
                let opts = RenderOptions {
                    depth: *depth,
                    ..Default::default()
                };
                // Depth needs the CPU renderer's per-pixel outputs.
                let mut gpu = match renderer.as_deref_mut() {
                    Some(g) if !*depth => Some((g, Arc::new(scene.clone()))),
                    _ => None,
                };
                for (i, fr) in cams.frames.iter().enumerate() {
                    self.progress.set("rendering", i as u64, cams.frames.len() as u64);
                    let cam = fr.camera.downscaled(*downscale);
                    let p = dir.join(format!("{}.png", fr.base_name()));
                    if let Some((g, shared)) = gpu.as_mut() {
                        let rgb = g.render_rgb(shared.clone(), &cam)?;
                        save_png(&p, cam.intrinsics.width, cam.intrinsics.height, &to_rgb8(&rgb))?;
                        out.files.push(p);
                        continue;
                    }
                    let frame = render(&scene, &cam, &opts)?;
                    save_png(&p, frame.width, frame.height, &to_rgb8(&frame.out.color))?;
                    out.files.push(p);
                    if *depth {
                        let c = crate::render::colorize_depth(&frame.out.depth, &frame.out.opacity);
                        let p = dir.join(format!("{}_depth.png", fr.base_name()));
                        save_png(&p, frame.width, frame.height, &to_rgb8(&c))?;
                        out.files.push(p);
                    }
                }
            }
            Command::Export(e) => self.export(e, &mut out)?,
            _ => unreachable!("edits are not outputs"),
        }
        out.message = format!("wrote {} files", out.files.len());
        Ok(out)
    }

    fn export(&self, e: &Export, out: &mut StepOutput) -> Result<()> {
        match e {
            Export::Masks {
                object,
                cameras,
                out: dir,
                downscale,
            } => {
                ensure!(*downscale >= 1, "downscale must be at least 1");
                let cams = self.cameras(cameras)?;
                let (scene, shown) = scene_of(&self.state);
                let oi = self
                    .state
                    .objects
                    .iter()
                    .position(|o| &o.name == object)
                    .ok_or_else(|| unknown("object", object, &self.state))?;
                let probe = shown[oi].clone().ok_or_else(|| {
                    Error::invalid(format!("object '{object}' is removed or hidden: it has no 2D mask"))
                })?;
                let opts = RenderOptions {
                    probes: vec![probe],
                    depth: false,
                    ..Default::default()
                };
                let dir = self.output_path(dir);
                for (i, fr) in cams.frames.iter().enumerate() {
                    self.progress.set("exporting masks", i as u64, cams.frames.len() as u64);
                    let f = render(&scene, &fr.camera.downscaled(*downscale), &opts)?;
                    let m: Vec<u8> = f
                        .out
                        .probe_opacity
                        .iter()
                        .flat_map(|&v| [if v > 0.1 { 255 } else { 0 }; 3])
                        .collect();
                    let p = dir.join(format!("{}_mask.png", fr.base_name()));
                    save_png(&p, f.width, f.height, &m)?;
                    out.files.push(p);
                }
            }
            Export::ObjectField {
                object,
                out: path,
                margin,
            } => {
                let o = self.object(object)?;
                let f = self.field(&o.field)?;
                let cropped = crate::edit::crop::object_field(&f.field, &o.mask, *margin)?;
                let p = self.output_path(path);
                cropped.save(&p)?;
                out.files.push(p);
            }
            Export::Mesh { target, out: path, iso } => {
                use crate::edit::mesh::{export_mesh, field_mesh, MeshOptions};
                self.progress.set("extracting the mesh", 0, 0);
                let mesh = if let Ok(f) = self.field(target) {
                    field_mesh(
                        &f.field,
                        &MeshOptions {
                            iso: *iso,
                            object: None,
                            transform: Some(f.transform),
                        },
                    )?
                } else {
                    let o = self.object(target)?;
                    let f = self.field(&o.field)?;
                    let t = o.transform * f.transform;
                    field_mesh(
                        &f.field,
                        &MeshOptions {
                            iso: *iso,
                            object: Some(&o.mask),
                            transform: Some(t),
                        },
                    )?
                };
                let p = self.output_path(path);
                export_mesh(&mesh, &p)?;
                out.files.push(p);
            }
            Export::Bitmap { object, out: path } => {
                let o = self.object(object)?;
                let p = self.output_path(path);
                crate::segment::bitmap_file::save_bitmap(&p, &o.mask, &o.name)?;
                out.files.push(p);
            }
            Export::Composition { out: path } => {
                let p = self.output_path(path);
                out.files.extend(super::composition::save(self, &p)?);
            }
            Export::Script { out: path } => {
                let p = self.output_path(path);
                super::script::save_script(&super::Script { commands: self.log() }, &p)?;
                out.files.push(p);
            }
        }
        Ok(())
    }

    /// Restores a state (used when opening a composition).
    pub fn set_state(&mut self, st: State) {
        self.state = st;
        self.undo.clear();
        self.redo.clear();
    }
}

/// Scene of a state plus, per object, the probe that measures its 2D mask
/// (`None` when removed or hidden).
pub fn scene_of(st: &State) -> (Scene, Vec<Option<Probe>>) {
    let fields: Vec<FieldPlacement> = st
        .fields
        .iter()
        .map(|f| FieldPlacement {
            field: f.field.clone(),
            transform: f.transform,
            visible: f.visible,
        })
        .collect();
    let objects: Vec<ObjectPlacement> = st
        .objects
        .iter()
        .filter_map(|o| {
            let fi = st.fields.iter().position(|f| f.name == o.field)?;
            Some(ObjectPlacement {
                field: fi,
                mask: o.mask.clone(),
                transform: o.transform,
                removed: o.removed,
                visible: o.visible,
                duplicate: o.duplicate,
                color_edit: o.color_edit,
            })
        })
        .collect();
    let scene = compose(&fields, &objects, Vec3::from(st.background));
    // Find each object's layer: its own Keep layer if detached, else its
    // field's layer (probe with its bitmap).
    let probes = st
        .objects
        .iter()
        .map(|o| {
            if o.removed || !o.visible {
                return None;
            }
            let f = st.fields.iter().find(|f| f.name == o.field)?;
            let own = scene.layers.iter().position(|l| {
                matches!(&l.mask, crate::render::Mask::Keep(m) if Arc::ptr_eq(m, &o.mask))
                    && Arc::ptr_eq(&l.field, &f.field)
                    && l.to_world == o.transform * f.transform
            });
            let layer = own.or_else(|| {
                scene.layers.iter().position(|l| {
                    Arc::ptr_eq(&l.field, &f.field)
                        && l.to_world == f.transform
                        && !matches!(l.mask, crate::render::Mask::Keep(_))
                })
            })?;
            Some(Probe {
                layer,
                mask: o.mask.clone(),
            })
        })
        .collect();
    (scene, probes)
}

fn unknown(kind: &str, name: &str, st: &State) -> Error {
    let names: Vec<&str> = if kind == "field" {
        st.fields.iter().map(|f| f.name.as_str()).collect()
    } else {
        st.objects.iter().map(|o| o.name.as_str()).collect()
    };
    Error::invalid(format!(
        "no {kind} named '{name}' (there are: {})",
        if names.is_empty() {
            "none".into()
        } else {
            names.join(", ")
        }
    ))
}

fn find_field<'a>(st: &'a State, name: &str) -> R<&'a FieldEntry> {
    st.fields
        .iter()
        .find(|f| f.name == name)
        .ok_or_else(|| unknown("field", name, st))
}
fn find_field_mut<'a>(st: &'a mut State, name: &str) -> R<&'a mut FieldEntry> {
    let err = unknown("field", name, st);
    st.fields.iter_mut().find(|f| f.name == name).ok_or(err)
}
fn find_object<'a>(st: &'a State, name: &str) -> R<&'a ObjectEntry> {
    st.objects
        .iter()
        .find(|o| o.name == name)
        .ok_or_else(|| unknown("object", name, st))
}
fn find_object_mut<'a>(st: &'a mut State, name: &str) -> R<&'a mut ObjectEntry> {
    let err = unknown("object", name, st);
    st.objects.iter_mut().find(|o| o.name == name).ok_or(err)
}

/// Names are unique across fields and objects so that `target` is unambiguous.
fn check_new_name(st: &State, name: &str) -> R<()> {
    ensure!(!name.trim().is_empty(), "names must not be empty");
    ensure!(
        !st.fields.iter().any(|f| f.name == name) && !st.objects.iter().any(|o| o.name == name),
        "the name '{name}' is already used"
    );
    Ok(())
}

/// World-space centre of an object as currently placed.
fn object_pivot(st: &State, object: &str) -> R<Vec3> {
    let o = find_object(st, object)?;
    let f = find_field(st, &o.field)?;
    let t = o.transform * f.transform;
    Ok(object_center(&f.field, &o.mask, &t).unwrap_or_else(|| t.transform_point3(f.field.bounds().center())))
}

/// The transform spec that moves by `t` (helper for the editor and tests).
pub fn translate(t: Vec3) -> TransformSpec {
    TransformSpec::translation(t)
}
