//! The session's model: fields and objects with stable ids, their
//! placements, the segmentation parameters. Ids identify; names are labels
//! that commands and users refer to and that may change (`rename`).
//!
//! Plain data: cloning a state shares its grids and bitmaps (`Arc`), which
//! is what makes an undo step cheap.

use super::FieldSource;
use crate::camera::{Camera, CameraSet};
use crate::demo::DemoObject;
use crate::edit::compose::{compose, object_center, Composed, FieldInput, ObjectInput};
pub use crate::edit::compose::{Placement, Shown};
use crate::error::{Error, Result};
use crate::field::{Bitmap, Field};
use crate::render::{Probe, Scene};
use crate::segment::SegmentParams;
use glam::Vec3;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

/// Ids are unique in the process and never reused, so that an entity or a
/// selection holding one can never point at a different object later.
static NEXT_ID: AtomicU64 = AtomicU64::new(1);

fn next_id() -> u64 {
    NEXT_ID.fetch_add(1, Ordering::Relaxed)
}

/// A field's identity, stable across renames.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct FieldId(u64);

/// An object's identity, stable across renames.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ObjectId(u64);

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
    pub id: FieldId,
    pub name: String,
    pub source: FieldSource,
    pub field: Arc<Field>,
    pub placement: Placement,
    pub demo: Option<Arc<DemoInfo>>,
}

#[derive(Clone, Debug)]
pub struct ObjectEntry {
    pub id: ObjectId,
    pub name: String,
    /// The field it was cut from.
    pub field: FieldId,
    pub mask: Arc<Bitmap>,
    pub placement: Placement,
}

/// Everything undo/redo restores. Cloning shares grids and bitmaps.
#[derive(Clone, Debug)]
pub struct State {
    pub fields: Vec<FieldEntry>,
    pub objects: Vec<ObjectEntry>,
    pub params: SegmentParams,
    pub background: [f32; 3],
}

impl Default for State {
    fn default() -> Self {
        State {
            fields: vec![],
            objects: vec![],
            params: SegmentParams::default(),
            background: [1.0; 3],
        }
    }
}

impl State {
    /// Adds a field under a new id.
    pub fn add_field(
        &mut self,
        name: &str,
        source: FieldSource,
        field: Arc<Field>,
        placement: Placement,
        demo: Option<Arc<DemoInfo>>,
    ) -> FieldId {
        let id = FieldId(next_id());
        self.fields.push(FieldEntry {
            id,
            name: name.into(),
            source,
            field,
            placement,
            demo,
        });
        id
    }

    /// Adds an object of field `field` under a new id.
    pub fn add_object(&mut self, name: &str, field: FieldId, mask: Arc<Bitmap>, placement: Placement) -> ObjectId {
        let id = ObjectId(next_id());
        self.objects.push(ObjectEntry {
            id,
            name: name.into(),
            field,
            mask,
            placement,
        });
        id
    }

    pub fn field(&self, id: FieldId) -> Option<&FieldEntry> {
        self.fields.iter().find(|f| f.id == id)
    }
    pub fn object(&self, id: ObjectId) -> Option<&ObjectEntry> {
        self.objects.iter().find(|o| o.id == id)
    }
    pub(crate) fn field_mut(&mut self, id: FieldId) -> Option<&mut FieldEntry> {
        self.fields.iter_mut().find(|f| f.id == id)
    }
    pub(crate) fn object_mut(&mut self, id: ObjectId) -> Option<&mut ObjectEntry> {
        self.objects.iter_mut().find(|o| o.id == id)
    }

    /// The field named `name`, or an error listing the fields there are.
    pub fn field_named(&self, name: &str) -> Result<&FieldEntry> {
        self.fields
            .iter()
            .find(|f| f.name == name)
            .ok_or_else(|| self.unknown("field", name))
    }
    /// The object named `name`, or an error listing the objects there are.
    pub fn object_named(&self, name: &str) -> Result<&ObjectEntry> {
        self.objects
            .iter()
            .find(|o| o.name == name)
            .ok_or_else(|| self.unknown("object", name))
    }
    /// The field an object was cut from.
    pub fn field_of(&self, o: &ObjectEntry) -> Result<&FieldEntry> {
        self.field(o.field)
            .ok_or_else(|| Error::invalid(format!("object '{}' has lost its field", o.name)))
    }

    fn unknown(&self, kind: &'static str, name: &str) -> Error {
        let names: Vec<&str> = if kind == "field" {
            self.fields.iter().map(|f| f.name.as_str()).collect()
        } else {
            self.objects.iter().map(|o| o.name.as_str()).collect()
        };
        Error::unknown_name(kind, name, &names)
    }

    /// Whether a field or an object is called `name`.
    pub fn name_used(&self, name: &str) -> bool {
        self.fields.iter().any(|f| f.name == name) || self.objects.iter().any(|o| o.name == name)
    }

    /// Names are unique across fields and objects so that `target` is
    /// unambiguous.
    pub fn check_new_name(&self, name: &str) -> Result<()> {
        crate::ensure!(!name.trim().is_empty(), "names must not be empty");
        crate::ensure!(!self.name_used(name), "the name '{name}' is already used");
        Ok(())
    }

    /// The composition: the scene, and the layer showing each object (in
    /// the order of `objects`).
    pub fn compose(&self) -> Composed {
        let fields: Vec<FieldInput> = self
            .fields
            .iter()
            .map(|f| FieldInput {
                field: &f.field,
                placement: &f.placement,
            })
            .collect();
        let objects: Vec<ObjectInput> = self
            .objects
            .iter()
            .map(|o| ObjectInput {
                // An object whose field is gone is simply not shown.
                field: self.fields.iter().position(|f| f.id == o.field).unwrap_or(usize::MAX),
                mask: &o.mask,
                placement: &o.placement,
            })
            .collect();
        compose(&fields, &objects, Vec3::from(self.background))
    }

    /// The composition as a renderable scene.
    pub fn scene(&self) -> Scene {
        self.compose().scene
    }

    /// The probe measuring object `id`'s 2D mask in `composed` (this
    /// state's composition), `None` when it is not shown.
    pub fn probe(&self, composed: &Composed, id: ObjectId) -> Option<Probe> {
        let i = self.objects.iter().position(|o| o.id == id)?;
        composed.probe(i, &self.objects[i].mask)
    }

    /// World-space centre of an object as currently placed (the default
    /// pivot of its transforms).
    pub fn object_pivot(&self, o: &ObjectEntry) -> Result<Vec3> {
        let f = self.field_of(o)?;
        let t = o.placement.transform * f.placement.transform;
        Ok(object_center(&f.field, &o.mask, &t).unwrap_or_else(|| t.transform_point3(f.field.bounds().center())))
    }
}
