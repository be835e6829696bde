//! Fields and segmented objects as entities, and the scene the ray marcher
//! draws.
//!
//! The editing [`Session`](crate::command::Session) is the model; entities
//! mirror its state so that systems and panels work on components: a field
//! entity holds its grids (`Arc`, so moving or duplicating copies nothing)
//! and a `Transform` (field-local → world); an object entity holds its
//! bitmap over its source field's grid, a relation to that field entity, its
//! `Transform` (applied after the field's: identity = where it was cut
//! from) and its colour edit. While the user drags a transform or an
//! appearance slider, the entities run ahead of the session (a preview);
//! the scene is built from the session's state with those previews applied,
//! by the same `command::session::scene_of` the scripts use.

use crate::command::session::{scene_of, State};
use crate::field::{Bitmap, Field};
use crate::render::{ColorEdit, Layer, Mask, Scene};
use crate::Result;
use bevy::prelude::*;
use glam::Affine3A;
use std::sync::Arc;

use super::gpu::pack::Overlay;

/// The name of a field or object in the session (names are unique).
#[derive(Component, Clone, Debug, PartialEq, Eq)]
pub struct SessionName(pub String);

/// A radiance field entity.
#[derive(Component, Clone)]
pub struct FieldLayer {
    pub field: Arc<Field>,
    pub hidden: bool,
}

/// A segmented object entity (relation to its field + its mask).
#[derive(Component, Clone)]
pub struct ObjectLayer {
    pub field: Entity,
    pub bitmap: Arc<Bitmap>,
    pub color_edit: ColorEdit,
    pub hidden: bool,
    /// Removed from the scene: its voxels stay cut from the field.
    pub removed: bool,
    /// A copy, which does not cut its source.
    pub duplicate: bool,
}

/// The selected field or object.
#[derive(Component, Clone, Copy, Default)]
pub struct Selected;

/// How the overlay shows the selection.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct OverlayMode {
    pub tint_selected: bool,
    pub dim_others: bool,
}

/// Per-object previews the entities hold ahead of the session.
#[derive(Clone, Debug, PartialEq)]
pub struct Preview {
    pub object: String,
    pub transform: Affine3A,
    pub color_edit: ColorEdit,
}

/// Remembers unions of bitmaps keyed by the bitmaps' identities, so that
/// rebuilding the scene (e.g. every frame of a drag) reuses the same `Arc`.
#[derive(Default)]
pub struct CutCache {
    entries: Vec<(Vec<usize>, Arc<Bitmap>)>,
}

impl CutCache {
    pub fn union(&mut self, bitmaps: &[&Arc<Bitmap>]) -> Result<Arc<Bitmap>> {
        let key: Vec<usize> = bitmaps.iter().map(|b| Arc::as_ptr(b) as usize).collect();
        if let Some((_, b)) = self.entries.iter().find(|(k, _)| *k == key) {
            return Ok(b.clone());
        }
        let mut c = bitmaps[0].as_ref().clone();
        for b in &bitmaps[1..] {
            c.union_with(b)?;
        }
        let c = Arc::new(c);
        if self.entries.len() > 16 {
            self.entries.remove(0);
        }
        self.entries.push((key, c.clone()));
        Ok(c)
    }
}

/// The scene of `state` with `previews` applied, and the overlay: the
/// selected object drawn as its own tinted layer (split out of its field's
/// layer when it sits in place, which leaves the image unchanged), the
/// others dimmed on request.
pub fn build_scene(
    state: &State,
    previews: &[Preview],
    selected: Option<&str>,
    mode: OverlayMode,
    cuts: &mut CutCache,
) -> Result<(Scene, Vec<Overlay>)> {
    let mut st = state.clone();
    for p in previews {
        if let Some(o) = st.objects.iter_mut().find(|o| o.name == p.object) {
            o.transform = p.transform;
            o.color_edit = Some(p.color_edit).filter(|e| !e.is_identity());
        }
    }
    let (mut scene, probes) = scene_of(&st);
    let mut overlay = vec![Overlay::default(); scene.layers.len()];
    let sel = selected.and_then(|name| {
        let i = st.objects.iter().position(|o| o.name == name)?;
        Some((i, probes.get(i)?.clone()?))
    });
    let mut highlighted = None;
    if let Some((i, probe)) = sel.filter(|_| mode.tint_selected || mode.dim_others) {
        let own = matches!(&scene.layers[probe.layer].mask, Mask::Keep(m) if Arc::ptr_eq(m, &probe.mask));
        if own {
            highlighted = Some(probe.layer);
        } else {
            // Split the object out of its field's layer (exact at identity).
            let fl = &scene.layers[probe.layer];
            let cut = match &fl.mask {
                Mask::Remove(c) => cuts.union(&[c, &probe.mask])?,
                _ => probe.mask.clone(),
            };
            let part = Layer {
                field: fl.field.clone(),
                to_world: fl.to_world,
                mask: Mask::Keep(probe.mask.clone()),
                color_edit: st.objects[i].color_edit,
            };
            scene.layers[probe.layer].mask = Mask::Remove(cut);
            scene.layers.push(part);
            overlay.push(Overlay::default());
            highlighted = Some(scene.layers.len() - 1);
        }
    }
    if let Some(h) = highlighted {
        for (k, o) in overlay.iter_mut().enumerate() {
            o.highlight = k == h && mode.tint_selected;
            o.dim = k != h && mode.dim_others;
        }
    }
    Ok((scene, overlay))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::command::session::{FieldEntry, ObjectEntry};
    use crate::command::FieldSource;
    use crate::field::{Aabb, FieldBuilder};
    use glam::Vec3;

    fn state() -> State {
        let f = Arc::new(
            FieldBuilder::new(Aabb::new(Vec3::splat(-1.0), Vec3::ONE), [9, 9, 9]).build(|_| 1.0, |_| Vec3::ONE, None),
        );
        let mut mask = Bitmap::new(f.res());
        mask.set(40, true);
        State {
            fields: vec![FieldEntry {
                name: "f".into(),
                source: FieldSource::File("f.safetensors".into()),
                field: f,
                transform: Affine3A::IDENTITY,
                visible: true,
                demo: None,
            }],
            objects: vec![ObjectEntry {
                name: "o".into(),
                field: "f".into(),
                mask: Arc::new(mask),
                transform: Affine3A::IDENTITY,
                removed: false,
                visible: true,
                duplicate: false,
                color_edit: None,
            }],
            params: Default::default(),
            background: [1.0; 3],
        }
    }

    #[test]
    fn selecting_an_in_place_object_splits_it_out_exactly() {
        let st = state();
        let mode = OverlayMode {
            tint_selected: true,
            dim_others: false,
        };
        let mut cuts = CutCache::default();
        let (plain, _) = build_scene(&st, &[], None, mode, &mut cuts).unwrap();
        assert_eq!(plain.layers.len(), 1, "an untouched object stays in its field");
        let (scene, ov) = build_scene(&st, &[], Some("o"), mode, &mut cuts).unwrap();
        assert_eq!(scene.layers.len(), 2);
        assert!(matches!(&scene.layers[0].mask, Mask::Remove(c) if c.get(40) && c.count() == 1));
        assert!(matches!(&scene.layers[1].mask, Mask::Keep(k) if k.get(40)));
        assert!(ov[1].highlight && !ov[0].highlight);
        // Same cut again: the cached Arc is reused.
        let (again, _) = build_scene(&st, &[], Some("o"), mode, &mut cuts).unwrap();
        let ptr = |s: &Scene| match &s.layers[0].mask {
            Mask::Remove(c) => Arc::as_ptr(c),
            _ => std::ptr::null(),
        };
        assert_eq!(ptr(&scene), ptr(&again));
    }

    #[test]
    fn previews_move_objects_before_the_session_does() {
        let st = state();
        let p = Preview {
            object: "o".into(),
            transform: Affine3A::from_translation(Vec3::X),
            color_edit: ColorEdit::default(),
        };
        let (scene, _) = build_scene(&st, &[p], None, OverlayMode::default(), &mut CutCache::default()).unwrap();
        assert_eq!(scene.layers.len(), 2);
        assert_eq!(scene.layers[1].to_world, Affine3A::from_translation(Vec3::X));
    }
}
