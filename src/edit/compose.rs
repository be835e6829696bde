//! From fields and segmented objects to a renderable scene (DESIGN.md, Edits).
//!
//! Plain data in, [`Composed`] out: the scene and, for every object, the
//! layer that shows it, so nothing downstream has to find an object's layer
//! again by comparing masks or transforms.
//! - a field renders with its density multiplied by (1 − b) for the union b
//!   of its *detached* objects' bitmaps (removed, moved, recoloured, or shown
//!   while the field is hidden), so a moved object leaves no copy behind;
//! - every detached object that is not removed renders as its own layer
//!   (σ·b of its source field) at `object.transform · field.transform`, i.e.
//!   a point x of the world is sampled at A⁻¹x in the source;
//! - duplicates are objects that do not cut their source;
//! - an object that is not detached is left inside its field's layer, so an
//!   untouched segmentation renders exactly like the field.
//!
//! Layers composite D²NeRF-style in the renderer.

use crate::field::{Bitmap, Field};
use crate::render::{ColorEdit, Layer, Mask, Probe, Scene};
use glam::{Affine3A, Vec3};
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Where and how a field or an object is shown: the one declaration of
/// placement used by the session, the composition document (flattened into
/// each object's entry), the editor's entities and [`compose`]. Fields use
/// `transform` and `visible` only.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Placement {
    /// Fields: field-local → world. Objects: applied after their field's
    /// (identity = where it was cut from). Row-major 4×4 on disk.
    #[serde(with = "crate::util::rows")]
    pub transform: Affine3A,
    pub visible: bool,
    /// Cut from its field and not shown.
    #[serde(default)]
    pub removed: bool,
    /// A copy: it never cuts its source.
    #[serde(default)]
    pub duplicate: bool,
    #[serde(default)]
    pub color_edit: Option<ColorEdit>,
}

impl Default for Placement {
    fn default() -> Self {
        Placement {
            transform: Affine3A::IDENTITY,
            visible: true,
            removed: false,
            duplicate: false,
            color_edit: None,
        }
    }
}

impl Placement {
    /// Shown in its own layer rather than inside its field's.
    fn detached(&self, field_visible: bool) -> bool {
        self.removed
            || self.duplicate
            || !self.visible
            || !field_visible
            || self.transform != Affine3A::IDENTITY
            || self.color_edit.is_some_and(|e| !e.is_identity())
    }
}

/// A field to compose.
#[derive(Clone, Copy, Debug)]
pub struct FieldInput<'a> {
    pub field: &'a Arc<Field>,
    pub placement: &'a Placement,
}

/// An object to compose.
#[derive(Clone, Copy, Debug)]
pub struct ObjectInput<'a> {
    /// Index into the field list.
    pub field: usize,
    pub mask: &'a Arc<Bitmap>,
    pub placement: &'a Placement,
}

/// The layer that shows an object.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shown {
    pub layer: usize,
    /// The object's own layer (a `Keep` of its mask); otherwise it sits
    /// inside its field's layer, among the rest of the field.
    pub own: bool,
}

/// A composed scene and, per object (in input order), the layer showing it
/// (`None` when removed or hidden).
#[derive(Clone, Debug)]
pub struct Composed {
    pub scene: Scene,
    pub objects: Vec<Option<Shown>>,
}

impl Composed {
    /// The probe that measures object `i`'s 2D mask, if it is shown.
    pub fn probe(&self, i: usize, mask: &Arc<Bitmap>) -> Option<Probe> {
        let shown = (*self.objects.get(i)?)?;
        Some(Probe {
            layer: shown.layer,
            mask: mask.clone(),
        })
    }
}

/// Builds the layers for a composition (see the module docs).
pub fn compose(fields: &[FieldInput], objects: &[ObjectInput], background: Vec3) -> Composed {
    let mut layers = vec![];
    let mut field_layer = vec![None; fields.len()];
    for (fi, f) in fields.iter().enumerate() {
        if !f.placement.visible {
            continue;
        }
        let cuts = objects
            .iter()
            .filter(|o| o.field == fi && !o.placement.duplicate && o.placement.detached(true));
        let mut layer = Layer::new(f.field.clone());
        layer.to_world = f.placement.transform;
        if let Some(c) = union(cuts.map(|o| o.mask)) {
            layer.mask = Mask::Remove(Arc::new(c));
        }
        field_layer[fi] = Some(layers.len());
        layers.push(layer);
    }
    let mut shown = Vec::with_capacity(objects.len());
    for o in objects {
        let Some(f) = fields.get(o.field) else {
            shown.push(None);
            continue;
        };
        let p = o.placement;
        if p.removed || !p.visible {
            shown.push(None);
        } else if p.detached(f.placement.visible) {
            shown.push(Some(Shown {
                layer: layers.len(),
                own: true,
            }));
            layers.push(Layer {
                field: f.field.clone(),
                to_world: p.transform * f.placement.transform,
                mask: Mask::Keep(o.mask.clone()),
                color_edit: p.color_edit,
            });
        } else {
            shown.push(field_layer[o.field].map(|layer| Shown { layer, own: false }));
        }
    }
    Composed {
        scene: Scene { layers, background },
        objects: shown,
    }
}

/// Union of bitmaps over one field (`None` for none).
fn union<'a>(mut masks: impl Iterator<Item = &'a Arc<Bitmap>>) -> Option<Bitmap> {
    let mut cut = (**masks.next()?).clone();
    for m in masks {
        // Same field, same resolution: union cannot fail.
        cut.union_with(m).expect("object bitmaps match their field");
    }
    Some(cut)
}

/// World-space centre of an object's voxels' bounding box (the default pivot
/// for rotations and scaling).
pub fn object_center(field: &Field, mask: &Bitmap, to_world: &Affine3A) -> Option<Vec3> {
    let (lo, hi) = mask.bounding_box()?;
    let g = field.geom();
    let c = 0.5 * (g.point(lo[0], lo[1], lo[2]) + g.point(hi[0], hi[1], hi[2]));
    Some(to_world.transform_point3(c))
}
