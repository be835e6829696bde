//! The editing session: the state machine of [`Edit`]s. `apply` is the one
//! entry point that changes the state; `undo` / `redo` move along the
//! history, which keeps at most [`Session::undo_limit`] steps. Outputs
//! (render, export, save) are not here: they read a session
//! (`command::output`).
//!
//! A *dry* session ([`Session::dry`]) applies the same rules without the
//! expensive work (field grids, segmentation, growth): it is how a script is
//! checked before it runs, so a check and a run cannot disagree.

use super::state::{DemoInfo, FieldEntry, ObjectEntry, ObjectId, Placement, State};
use super::{Edit, FieldSource, StrokeSource};
use crate::demo::STROKE_RADIUS;
use crate::error::{Error, Result};
use crate::field::{Aabb, Bitmap, Field, FieldBuilder};
use crate::render::{Layer, Scene};
use crate::segment::{
    load_strokes_in, mask_bound, scribble_stroke, Grower, Growth, MaskBuilder, Polarity, SegmentParams, Stroke,
    Timings, MAX_GROW_STEPS,
};
use crate::util::Progress;
use glam::{Affine3A, Vec2, Vec3};
use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// How many edits undo reaches back by default.
pub const DEFAULT_UNDO_LIMIT: usize = 100;

/// What one command produced.
#[derive(Clone, Debug, Default)]
pub struct StepOutput {
    pub files: Vec<PathBuf>,
    pub message: String,
    pub timings: Option<Timings>,
}

#[derive(Debug)]
pub struct Session {
    state: State,
    /// States before the last edits, oldest first (at most `undo_limit`).
    history: VecDeque<State>,
    /// Every edit applied since the start (undone ones excluded): the edit
    /// log, which outlives the bounded history.
    log: Vec<Edit>,
    redo: Vec<(State, Edit)>,
    undo_limit: usize,
    /// Check the rules only (see the module docs).
    dry: bool,
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
        Session::with_state(base_dir, out_dir, State::default())
    }

    /// A session that starts from `state` (an opened composition).
    pub fn with_state(base_dir: impl Into<PathBuf>, out_dir: impl Into<PathBuf>, state: State) -> Self {
        Session {
            state,
            history: VecDeque::new(),
            log: vec![],
            redo: vec![],
            undo_limit: DEFAULT_UNDO_LIMIT,
            dry: false,
            base_dir: base_dir.into(),
            out_dir: out_dir.into(),
            progress: Progress::default(),
        }
    }

    /// A session that checks edits without doing their work: fields are
    /// read as far as their headers (grids stand in at the smallest size),
    /// strokes are read and checked but not segmented, growth does nothing.
    pub fn dry(base_dir: impl Into<PathBuf>) -> Self {
        let mut s = Session::new(base_dir, ".");
        s.dry = true;
        s
    }

    /// Keeps at most `steps` edits to undo (older states are dropped, and
    /// with them the grids of fields deleted before them).
    pub fn with_undo_limit(mut self, steps: usize) -> Self {
        self.undo_limit = steps;
        self.trim_history();
        self
    }
    pub fn undo_limit(&self) -> usize {
        self.undo_limit
    }

    pub fn state(&self) -> &State {
        &self.state
    }
    /// The edits applied so far, oldest first (undone ones excluded).
    pub fn log(&self) -> &[Edit] {
        &self.log
    }
    pub fn can_undo(&self) -> bool {
        !self.history.is_empty()
    }
    pub fn can_redo(&self) -> bool {
        !self.redo.is_empty()
    }
    /// Undoes the last edit; returns it.
    pub fn undo(&mut self) -> Option<Edit> {
        let prev = self.history.pop_back()?;
        let edit = self.log.pop().expect("every undo step has its edit in the log");
        let cur = std::mem::replace(&mut self.state, prev);
        self.redo.push((cur, edit.clone()));
        Some(edit)
    }
    pub fn redo(&mut self) -> Option<Edit> {
        let (next, edit) = self.redo.pop()?;
        let cur = std::mem::replace(&mut self.state, next);
        self.push_history(cur, edit.clone());
        Some(edit)
    }

    /// Validates and performs an edit: the previous state goes on the undo
    /// history and the edit on the log. On error nothing changes.
    pub fn apply(&mut self, edit: &Edit) -> Result<StepOutput> {
        let mut next = self.state.clone();
        let out = self.edit(&mut next, edit);
        self.progress.clear();
        let out = out?;
        let prev = std::mem::replace(&mut self.state, next);
        self.push_history(prev, edit.clone());
        self.redo.clear();
        Ok(out)
    }

    fn push_history(&mut self, prev: State, edit: Edit) {
        self.history.push_back(prev);
        self.log.push(edit);
        self.trim_history();
    }
    fn trim_history(&mut self) {
        while self.history.len() > self.undo_limit {
            self.history.pop_front();
        }
    }

    // ---------------------------------------------------------------- lookups

    pub fn field(&self, name: &str) -> Result<&FieldEntry> {
        self.state.field_named(name)
    }
    pub fn object(&self, name: &str) -> Result<&ObjectEntry> {
        self.state.object_named(name)
    }
    /// An input path (fields, strokes, cameras) as the session reads it.
    pub fn resolve(&self, p: &Path) -> PathBuf {
        if p.is_absolute() {
            p.to_path_buf()
        } else {
            self.base_dir.join(p)
        }
    }
    /// An output path as the session writes it.
    pub fn output_path(&self, p: &Path) -> PathBuf {
        if p.is_absolute() {
            p.to_path_buf()
        } else {
            self.out_dir.join(p)
        }
    }

    /// The composition as a renderable scene.
    pub fn scene(&self) -> Scene {
        self.state.scene()
    }

    // ------------------------------------------------------------------ edits

    fn edit(&self, st: &mut State, edit: &Edit) -> Result<StepOutput> {
        let mut out = StepOutput::default();
        match edit {
            Edit::LoadField {
                name,
                source,
                transform,
            } => {
                st.check_new_name(name)?;
                self.progress.set(&format!("loading '{name}'"), 0, 0);
                let (field, demo) = self.load_source(source)?;
                let pivot = field.bounds().center();
                let transform = match transform {
                    Some(t) => {
                        t.validate()?;
                        t.affine(pivot)
                    }
                    None => Affine3A::IDENTITY,
                };
                out.message = format!("loaded '{name}' ({:?} grid)", field.res());
                let placement = Placement {
                    transform,
                    ..Default::default()
                };
                st.add_field(name, source.clone(), field, placement, demo);
            }
            Edit::TransformField { field, transform } => {
                transform.validate()?;
                let id = st.field_named(field)?.id;
                let f = st.field_mut(id).expect("found above");
                let pivot = f.placement.transform.transform_point3(f.field.bounds().center());
                f.placement.transform = transform.affine(pivot) * f.placement.transform;
            }
            Edit::SetParams { .. } => st.params = edit.merged_params(&st.params)?,
            Edit::Stroke {
                object,
                field,
                polarity,
                source,
            } => out = self.stroke(st, object, field.as_deref(), *polarity, source)?,
            Edit::Grow { object, steps } => out.message = self.grow(st, object, *steps)?,
            Edit::Remove { object } => object_mut(st, object)?.placement.removed = true,
            Edit::Restore { object } => object_mut(st, object)?.placement.removed = false,
            Edit::SetVisible { target, visible } => placement_mut(st, target)?.visible = *visible,
            Edit::Transform { object, transform } => {
                transform.validate()?;
                let pivot = st.object_pivot(st.object_named(object)?)?;
                let o = object_mut(st, object)?;
                o.placement.transform = transform.affine(pivot) * o.placement.transform;
            }
            Edit::Duplicate {
                object,
                name,
                transform,
            } => {
                st.check_new_name(name)?;
                let o = st.object_named(object)?;
                let mut placement = Placement {
                    duplicate: true,
                    removed: false,
                    ..o.placement
                };
                if let Some(t) = transform {
                    t.validate()?;
                    placement.transform = t.affine(st.object_pivot(o)?) * placement.transform;
                }
                let (field, mask) = (o.field, o.mask.clone());
                st.add_object(name, field, mask, placement);
            }
            Edit::Appearance { object, edit } => {
                edit.validate()?;
                object_mut(st, object)?.placement.color_edit = (!edit.is_identity()).then_some(*edit);
            }
            Edit::Rename { target, name } => {
                st.check_new_name(name)?;
                // Ids identify: only the label changes.
                if let Ok(f) = st.field_named(target) {
                    let id = f.id;
                    st.field_mut(id).expect("found above").name = name.clone();
                } else {
                    object_mut(st, target)?.name = name.clone();
                }
            }
            Edit::Delete { target } => {
                if let Ok(f) = st.field_named(target) {
                    let id = f.id;
                    st.fields.retain(|f| f.id != id);
                    st.objects.retain(|o| o.field != id);
                } else {
                    let id = st.object_named(target)?.id;
                    st.objects.retain(|o| o.id != id);
                }
            }
        }
        Ok(out)
    }

    fn load_source(&self, source: &FieldSource) -> Result<(Arc<Field>, Option<Arc<DemoInfo>>)> {
        match source {
            FieldSource::File(p) if self.dry => Ok((Arc::new(stand_in(&self.resolve(p))?), None)),
            FieldSource::File(p) => {
                let path = self.resolve(p);
                let field = Field::load(&path)?;
                // A field written before files kept up: its capture's cameras say it.
                let field = match field.up {
                    Some(_) => field,
                    None => field.or_up_from(crate::camera::set::capture_cameras(&path).as_ref()),
                };
                Ok((Arc::new(field), None))
            }
            FieldSource::Demo { scene, res, seed } => {
                crate::demo::check_res(*res)?;
                // A dry run needs the demo's cameras and objects, not its detail.
                let res = if self.dry { crate::demo::MIN_RES } else { *res };
                let d = crate::demo::build(scene, res, *seed)?;
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
                load_strokes_in(&self.resolve(p), cams.as_ref(), f.placement.transform)?
            }
            StrokeSource::Scribble { path, camera } => {
                vec![scribble_stroke(
                    &self.resolve(path),
                    camera.to_camera()?,
                    Polarity::Positive,
                    object,
                )?]
            }
            StrokeSource::Demo { object: demo_object } => vec![demo_stroke(f, object, demo_object)?],
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
        let f = match (&existing, field) {
            (Some(o), Some(name)) => {
                let f = st.field_of(o)?;
                if f.name != name {
                    return Err(Error::invalid(format!(
                        "object '{object}' belongs to field '{}', not '{name}'",
                        f.name
                    )));
                }
                f
            }
            (Some(o), None) => st.field_of(o)?,
            (None, Some(name)) => st.field_named(name)?,
            (None, None) => st
                .fields
                .first()
                .ok_or_else(|| Error::invalid("no field is loaded to stroke on"))?,
        }
        .clone();
        if existing.is_none() {
            st.check_new_name(object)?;
        }
        let strokes = self.strokes_of(&f, object, source)?;
        let (mask, total) = self.segment(&f, object, existing.as_ref(), &strokes, polarity, &st.params)?;
        let msg = format!(
            "'{object}': {} voxels (last stroke {:.0} ms)",
            mask.count(),
            total.total_ms()
        );
        match existing {
            Some(o) => st.object_mut(o.id).expect("it exists").mask = Arc::new(mask),
            None => {
                st.add_object(object, f.id, Arc::new(mask), Placement::default());
            }
        }
        Ok(StepOutput {
            message: msg,
            timings: Some(total),
            ..Default::default()
        })
    }

    /// Applies `strokes` in order to the mask of `existing` (or an empty
    /// one); a dry session only checks that a negative stroke has something
    /// to subtract from.
    fn segment(
        &self,
        f: &FieldEntry,
        object: &str,
        existing: Option<&ObjectEntry>,
        strokes: &[Stroke],
        polarity: Option<Polarity>,
        params: &SegmentParams,
    ) -> Result<(Bitmap, Timings)> {
        let exists = existing.is_some();
        let start = existing.map_or_else(|| Bitmap::new(f.field.res()), |o| (*o.mask).clone());
        let mut builder = MaskBuilder::new(start);
        let mut total = Timings::default();
        let mut made = exists;
        let cache = if self.dry {
            crate::field::cache::require_features(&f.field)?;
            None
        } else {
            self.progress.set("per-voxel features", 0, 0);
            let cache = f.field.feature_cache()?;
            // Made once per field, like the cache itself.
            self.progress.set("coarse per-voxel features and neighbours", 0, 0);
            crate::segment::prepare(&cache, params);
            Some(cache)
        };
        // Stroke features come from the field as it stands in the world.
        let scene = Scene::new(vec![Layer {
            to_world: f.placement.transform,
            ..Layer::new(f.field.clone())
        }]);
        for (i, s) in strokes.iter().enumerate() {
            self.progress
                .set(&format!("segmenting '{object}'"), i as u64, strokes.len() as u64);
            let pol = polarity.unwrap_or(s.polarity);
            let has_mask = if self.dry { made } else { builder.mask.any() };
            if !exists && pol == Polarity::Negative && !has_mask {
                return Err(Error::invalid(format!(
                    "a negative stroke needs an existing object: there is no '{object}' yet"
                )));
            }
            made |= pol == Polarity::Positive;
            if let Some(cache) = &cache {
                total = builder.stroke(&scene, cache, s, pol, params)?;
            }
        }
        Ok((builder.mask, total))
    }

    fn grow(&self, st: &mut State, object: &str, steps: Growth) -> Result<String> {
        let o = st.object_named(object)?.clone();
        if self.dry {
            crate::field::cache::require_features(&st.field_of(&o)?.field)?;
            return Ok(String::new());
        }
        let cache = st.field_of(&o)?.field.feature_cache()?;
        let mut mask = (*o.mask).clone();
        let mut g = Grower::new(&cache, st.params.grow);
        if let Some(b) = mask_bound(&cache, &mask, &st.params) {
            g = g.with_bound(b);
        }
        let total = match steps {
            Growth::Steps(n) => n as u64,
            Growth::Converge => 0,
        };
        let label = format!("growing '{object}'");
        let n = g.grow(&mut mask, steps, MAX_GROW_STEPS, |i| {
            self.progress.set(&label, i as u64, total)
        });
        let msg = format!("'{object}': {} -> {} voxels in {n} steps", o.mask.count(), mask.count());
        st.object_mut(o.id).expect("found above").mask = Arc::new(mask);
        Ok(msg)
    }
}

/// A field file as a dry session sees it: checked as far as its header,
/// with the header's bounds and feature channels over the smallest grid
/// (and the same error as loading it when it is missing).
fn stand_in(path: &Path) -> Result<Field> {
    std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    let (h, _) = crate::field::io::read_header(path)?;
    let [lo, hi] = h.bounds;
    let bounds = Aabb::new(Vec3::from(lo), Vec3::from(hi));
    let zero = |_: Vec3, out: &mut [f32]| out.fill(0.0);
    let channels = h.feature_channels();
    let features = (channels > 0).then_some((channels, &zero as &(dyn Fn(Vec3, &mut [f32]) + Sync)));
    let mut f = FieldBuilder::new(bounds, [2; 3]).build(|_| 0.0, |_| Vec3::ZERO, features);
    f.ndc = h.ndc;
    f.up = h.up.map(|u| Vec3::from(u).normalize());
    Ok(f)
}

/// The built-in stroke of demo object `demo_object`, for `object`.
fn demo_stroke(f: &FieldEntry, object: &str, demo_object: &str) -> Result<Stroke> {
    let info = f.demo.as_ref().ok_or_else(|| {
        Error::invalid(format!(
            "field '{}' is not a demo scene: it has no built-in strokes",
            f.name
        ))
    })?;
    let o = info.objects.iter().find(|o| o.name == demo_object).ok_or_else(|| {
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
    camera.c2w = f.placement.transform * camera.c2w;
    Ok(Stroke {
        camera,
        points: px,
        radius: STROKE_RADIUS,
        polarity: Polarity::Positive,
        object: object.into(),
        joined: true,
    })
}

fn object_mut<'a>(st: &'a mut State, name: &str) -> Result<&'a mut ObjectEntry> {
    let id: ObjectId = st.object_named(name)?.id;
    Ok(st.object_mut(id).expect("found above"))
}

/// The placement of the field or, failing that, the object named `target`.
fn placement_mut<'a>(st: &'a mut State, target: &str) -> Result<&'a mut Placement> {
    if let Ok(f) = st.field_named(target) {
        let id = f.id;
        return Ok(&mut st.field_mut(id).expect("found above").placement);
    }
    Ok(&mut object_mut(st, target)?.placement)
}

/// The transform spec that moves by `t` (helper for the editor and tests).
pub fn translate(t: Vec3) -> super::TransformSpec {
    super::TransformSpec::translation(t)
}
