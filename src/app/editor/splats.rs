//! The editor's splat menu entries: File → Import splats, Export → splats
//! of the selected object or the scene without it.

use super::session::EditorSession;
use crate::command::{output, Edit, Export, FieldSource, Output, Session, StepOutput};
use crate::splat::{import_file, ImportOptions};
use bevy_egui::egui;
use std::path::Path;

/// Imports a splat `.ply` into `<file>.safetensors` beside it and adds that
/// field to the session (the edit log records the field file). Runs as an
/// editor request, off the UI thread.
pub fn import(session: &mut Session, ply: &Path) -> crate::Result<StepOutput> {
    let out = ply.with_extension("safetensors");
    let (field, r) = import_file(ply, &ImportOptions::default())?;
    field.save(&out)?;
    let stem = ply
        .file_stem()
        .map_or("splats".into(), |s| s.to_string_lossy().into_owned());
    let load = Edit::LoadField {
        name: super::session::fresh_name(session.state(), &stem),
        source: FieldSource::File(out.clone()),
        transform: None,
    };
    let mut step = output::perform(session, &load.into(), None)?;
    step.message = format!(
        "imported {} Gaussians from {} ({} floaters left out) into {}",
        r.gaussians,
        ply.display(),
        r.outside,
        out.display()
    );
    step.files.push(out);
    Ok(step)
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
