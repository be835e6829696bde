//! Fields and segmented objects as entities, and the scene the ray marcher
//! draws.
//!
//! The editing [`Session`](crate::command::Session) is the model; entities
//! mirror its state, matched by id, so that systems and panels work on
//! components: a field entity holds its grids (`Arc`, so moving or
//! duplicating copies nothing) and a `Transform` (field-local → world); an
//! object entity holds its bitmap over its source field's grid, a relation
//! to that field entity, its `Transform` (applied after the field's:
//! identity = where it was cut from) and its [`Placement`]. While the user
//! drags a transform or an appearance slider, the entity's `Transform` and
//! `placement.color_edit` run ahead of the session (a preview); the scene
//! is the session's composition with those previews applied, by the same
//! `State::compose` the scripts use.

use crate::command::state::{FieldId, ObjectId, Placement, State};
use crate::field::{Bitmap, Field};
use crate::render::{ColorEdit, Scene};
use bevy::prelude::*;
use glam::Affine3A;
use std::sync::Arc;

use super::gpu::pack::Overlay;

/// The label of a field or object in the session (names are unique, and
/// may change: entities are matched by [`FieldLayer::id`] / [`ObjectLayer::id`]).
#[derive(Component, Clone, Debug, PartialEq, Eq)]
pub struct SessionName(pub String);

/// A radiance field entity.
#[derive(Component, Clone)]
pub struct FieldLayer {
    pub id: FieldId,
    pub field: Arc<Field>,
    pub placement: Placement,
}

/// A segmented object entity (relation to its field + its mask).
#[derive(Component, Clone)]
pub struct ObjectLayer {
    pub id: ObjectId,
    pub field: Entity,
    pub bitmap: Arc<Bitmap>,
    pub placement: Placement,
}

impl ObjectLayer {
    /// The colour edit shown (identity when none).
    pub fn color_edit(&self) -> ColorEdit {
        self.placement.color_edit.unwrap_or_default()
    }
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
    pub object: ObjectId,
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
    selected: Option<ObjectId>,
    mode: OverlayMode,
) -> (Scene, Vec<Overlay>) {
    let mut st = state.clone();
    for p in previews {
        if let Some(o) = st.objects.iter_mut().find(|o| o.id == p.object) {
            o.placement.transform = p.transform;
            o.placement.color_edit = Some(p.color_edit).filter(|e| !e.is_identity());
        }
    }
    let composed = st.compose();
    let mut overlay = vec![Overlay::default(); composed.scene.layers.len()];
    let shown = selected.and_then(|id| {
        let i = st.objects.iter().position(|o| o.id == id)?;
        Some((composed.objects[i]?, &st.objects[i].mask))
    });
    if let Some((shown, mask)) = shown.filter(|_| mode.tint_selected || mode.dim_others) {
        // Detached objects (moved, recoloured, ...) have a layer of their
        // own; one in place is the highlight mask of its field's.
        if !shown.own {
            overlay[shown.layer].highlight_mask = Some(mask.clone());
        }
        for (k, o) in overlay.iter_mut().enumerate() {
            // (With a highlight mask, a layer holds the object and the rest.)
            o.highlight = k == shown.layer && mode.tint_selected;
            o.dim = (k != shown.layer || o.highlight_mask.is_some()) && mode.dim_others;
        }
    }
    (composed.scene, overlay)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::command::FieldSource;
    use crate::field::{Aabb, FieldBuilder};
    use crate::render::Mask;
    use glam::Vec3;

    fn state() -> State {
        let f = Arc::new(
            FieldBuilder::new(Aabb::new(Vec3::splat(-1.0), Vec3::ONE), [9, 9, 9]).build(|_| 1.0, |_| Vec3::ONE, None),
        );
        let mut mask = Bitmap::new(f.res());
        mask.set(40, true);
        let mut st = State::default();
        let fid = st.add_field(
            "f",
            FieldSource::File("f.safetensors".into()),
            f,
            Placement::default(),
            None,
        );
        st.add_object("o", fid, Arc::new(mask), Placement::default());
        st
    }

    const TINT_AND_DIM: OverlayMode = OverlayMode {
        tint_selected: true,
        dim_others: true,
    };

    #[test]
    fn an_in_place_selection_is_a_highlight_mask_on_its_field_layer() {
        let st = state();
        let (plain, ov) = build_scene(&st, &[], None, TINT_AND_DIM);
        assert_eq!(plain.layers.len(), 1, "an untouched object stays in its field");
        assert_eq!(ov, vec![Overlay::default()]);
        let (scene, ov) = build_scene(&st, &[], Some(st.objects[0].id), TINT_AND_DIM);
        assert_eq!(scene.layers.len(), 1, "still one layer to march");
        assert!(matches!(scene.layers[0].mask, Mask::All));
        assert!(ov[0].highlight && ov[0].dim, "object tinted, the rest dimmed");
        assert!(Arc::ptr_eq(ov[0].highlight_mask.as_ref().unwrap(), &st.objects[0].mask));
    }

    /// A copy made with no transform shares the original's mask and sits
    /// where it does: selecting the original must not tint the copy.
    #[test]
    fn selecting_the_original_of_an_untransformed_copy_highlights_the_original() {
        let mut st = state();
        let o = st.objects[0].clone();
        let copy = Placement {
            duplicate: true,
            ..o.placement
        };
        st.add_object("copy", o.field, o.mask.clone(), copy);
        let (scene, ov) = build_scene(&st, &[], Some(o.id), TINT_AND_DIM);
        assert_eq!(scene.layers.len(), 2, "the field, and the copy's own layer");
        assert!(ov[0].highlight && ov[0].highlight_mask.is_some(), "{ov:?}");
        assert!(!ov[1].highlight && ov[1].dim, "the copy is one of the others: {ov:?}");
        let (_, ov) = build_scene(&st, &[], Some(st.objects[1].id), TINT_AND_DIM);
        assert!(ov[1].highlight && ov[1].highlight_mask.is_none(), "{ov:?}");
        assert!(!ov[0].highlight && ov[0].highlight_mask.is_none(), "{ov:?}");
    }

    #[test]
    fn previews_move_objects_before_the_session_does() {
        let st = state();
        let p = Preview {
            object: st.objects[0].id,
            transform: Affine3A::from_translation(Vec3::X),
            color_edit: ColorEdit::default(),
        };
        let (scene, _) = build_scene(&st, &[p], None, OverlayMode::default());
        assert_eq!(scene.layers.len(), 2);
        assert_eq!(scene.layers[1].to_world, Affine3A::from_translation(Vec3::X));
    }
}
