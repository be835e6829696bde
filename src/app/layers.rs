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
use crate::render::{ColorEdit, Mask, Scene};
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

/// The scene of `state` with `previews` applied, and the overlay: the
/// selected object tinted, the others dimmed on request. An object that
/// sits in place inside its field's layer is tinted there through a
/// highlight mask, so selecting it adds no layer to march.
pub fn build_scene(
    state: &State,
    previews: &[Preview],
    selected: Option<&str>,
    mode: OverlayMode,
) -> (Scene, Vec<Overlay>) {
    let mut st = state.clone();
    for p in previews {
        if let Some(o) = st.objects.iter_mut().find(|o| o.name == p.object) {
            o.transform = p.transform;
            o.color_edit = Some(p.color_edit).filter(|e| !e.is_identity());
        }
    }
    let (scene, probes) = scene_of(&st);
    let mut overlay = vec![Overlay::default(); scene.layers.len()];
    let sel = selected.and_then(|name| {
        let i = st.objects.iter().position(|o| o.name == name)?;
        Some((i, probes.get(i)?.clone()?))
    });
    let mut highlighted = None;
    if let Some((_, probe)) = sel.filter(|_| mode.tint_selected || mode.dim_others) {
        // Detached objects (moved, recoloured, ...) have a Keep layer of
        // their own; one in place is the highlight mask of its field's.
        let own = matches!(&scene.layers[probe.layer].mask, Mask::Keep(m) if Arc::ptr_eq(m, &probe.mask));
        if !own {
            overlay[probe.layer].highlight_mask = Some(probe.mask.clone());
        }
        highlighted = Some(probe.layer);
    }
    if let Some(h) = highlighted {
        for (k, o) in overlay.iter_mut().enumerate() {
            // (With a highlight mask, a layer holds the object and the rest.)
            o.highlight = k == h && mode.tint_selected;
            o.dim = (k != h || o.highlight_mask.is_some()) && mode.dim_others;
        }
    }
    (scene, overlay)
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
    fn an_in_place_selection_is_a_highlight_mask_on_its_field_layer() {
        let st = state();
        let mode = OverlayMode {
            tint_selected: true,
            dim_others: true,
        };
        let (plain, ov) = build_scene(&st, &[], None, mode);
        assert_eq!(plain.layers.len(), 1, "an untouched object stays in its field");
        assert_eq!(ov, vec![Overlay::default()]);
        let (scene, ov) = build_scene(&st, &[], Some("o"), mode);
        assert_eq!(scene.layers.len(), 1, "still one layer to march");
        assert!(matches!(scene.layers[0].mask, Mask::All));
        assert!(ov[0].highlight && ov[0].dim, "object tinted, the rest dimmed");
        assert!(Arc::ptr_eq(ov[0].highlight_mask.as_ref().unwrap(), &st.objects[0].mask));
    }

    #[test]
    fn previews_move_objects_before_the_session_does() {
        let st = state();
        let p = Preview {
            object: "o".into(),
            transform: Affine3A::from_translation(Vec3::X),
            color_edit: ColorEdit::default(),
        };
        let (scene, _) = build_scene(&st, &[p], None, OverlayMode::default());
        assert_eq!(scene.layers.len(), 2);
        assert_eq!(scene.layers[1].to_world, Affine3A::from_translation(Vec3::X));
    }
}
