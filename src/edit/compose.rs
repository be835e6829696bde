//! From fields and segmented objects to a renderable scene (DESIGN.md, Edits).
//!
//! Plain data in, [`Scene`] out:
//! - a field renders with its density multiplied by (1 − b) for the union b
//!   of its *detached* objects' bitmaps (removed, moved, recoloured, or shown
//!   while the field is hidden), so a moved object leaves no copy behind;
//! - every detached object that is not removed renders as its own layer
//!   (σ·b of its source field) at `object.transform · field.transform`, i.e.
//!   a point x of the world is sampled at A⁻¹x in the source;
//! - duplicates are objects that do not cut their source;
//! - an object that is not detached is left inside its field's layer, so an
//!   untouched segmentation renders exactly like the field.
//! Layers composite D²NeRF-style in the renderer.

use crate::field::{Bitmap, Field};
use crate::render::{ColorEdit, Layer, Mask, Scene};
use glam::{Affine3A, Vec3};
use std::sync::Arc;

#[derive(Clone, Debug)]
pub struct FieldPlacement {
    pub field: Arc<Field>,
    pub transform: Affine3A,
    pub visible: bool,
}

#[derive(Clone, Debug)]
pub struct ObjectPlacement {
    /// Index into the field list.
    pub field: usize,
    pub mask: Arc<Bitmap>,
    /// Applied after the field's transform (identity = where it was cut).
    pub transform: Affine3A,
    pub removed: bool,
    pub visible: bool,
    /// A copy: it never cuts its source.
    pub duplicate: bool,
    pub color_edit: Option<ColorEdit>,
}

impl ObjectPlacement {
    fn detached(&self, field_visible: bool) -> bool {
        self.removed
            || self.duplicate
            || !self.visible
            || !field_visible
            || self.transform != Affine3A::IDENTITY
            || self.color_edit.is_some_and(|e| !e.is_identity())
    }
}

/// Builds the layers for a composition (see the module docs).
pub fn compose(fields: &[FieldPlacement], objects: &[ObjectPlacement], background: Vec3) -> Scene {
    let mut layers = vec![];
    for (fi, f) in fields.iter().enumerate() {
        if !f.visible {
            continue;
        }
        let mut cut: Option<Bitmap> = None;
        for o in objects
            .iter()
            .filter(|o| o.field == fi && !o.duplicate && o.detached(f.visible))
        {
            match &mut cut {
                None => cut = Some((*o.mask).clone()),
                // Same field, same resolution: union cannot fail.
                Some(c) => c.union_with(&o.mask).expect("object bitmaps match their field"),
            }
        }
        let mut layer = Layer::new(f.field.clone());
        layer.to_world = f.transform;
        if let Some(c) = cut {
            layer.mask = Mask::Remove(Arc::new(c));
        }
        layers.push(layer);
    }
    for o in objects {
        let Some(f) = fields.get(o.field) else { continue };
        if o.removed || !o.visible || !o.detached(f.visible) {
            continue;
        }
        layers.push(Layer {
            field: f.field.clone(),
            to_world: o.transform * f.transform,
            mask: Mask::Keep(o.mask.clone()),
            color_edit: o.color_edit,
        });
    }
    Scene { layers, background }
}

/// World-space centre of an object's voxels' bounding box (the default pivot
/// for rotations and scaling).
pub fn object_center(field: &Field, mask: &Bitmap, to_world: &Affine3A) -> Option<Vec3> {
    let (lo, hi) = mask.bounding_box()?;
    let g = field.geom();
    let c = 0.5 * (g.point(lo[0], lo[1], lo[2]) + g.point(hi[0], hi[1], hi[2]));
    Some(to_world.transform_point3(c))
}
