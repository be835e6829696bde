//! The editor's splat menu entries: File → Import splats, Export → splats
//! of the selected object or the scene without it.

use super::session::EditorSession;
use super::state::EditorState;
use crate::command::{Edit, Export, FieldSource, Output};
use crate::splat::{import_file, ImportOptions};
use bevy_egui::egui;
use std::path::Path;

/// Imports a splat `.ply` into `<file>.safetensors` beside it and adds that
/// field to the composition (the script records the field file).
pub fn import(state: &mut EditorState, es: &mut EditorSession, ply: &Path) {
    let out = ply.with_extension("safetensors");
    let r = import_file(ply, &ImportOptions::default()).and_then(|(f, r)| f.save(&out).map(|_| r));
    match r {
        Ok(r) => {
            state.status = format!(
                "imported {} Gaussians from {} ({} floaters left out) into {}",
                r.gaussians,
                ply.display(),
                r.outside,
                out.display()
            );
            let stem = ply
                .file_stem()
                .map_or("splats".into(), |s| s.to_string_lossy().into_owned());
            es.apply(Edit::LoadField {
                name: es.fresh_name(&stem),
                source: FieldSource::File(out),
                transform: None,
            });
        }
        Err(e) => state.error(format!("import of {} failed: {e}", ply.display())),
    }
}

/// Export → the object's splats, or the scene without it, to `out`.
pub fn export_buttons(ui: &mut egui::Ui, es: &mut EditorSession, object: &str, out: &Path) {
    for (label, complement) in [
        ("Splats of the object (.ply)", false),
        ("Splats of the scene without it (.ply)", true),
    ] {
        if ui.button(label).clicked() {
            es.apply(Output::Export(Export::Splats {
                object: object.to_string(),
                out: out.to_path_buf(),
                complement,
            }));
        }
    }
}
