//! A small in-editor file browser for the File / Export menus: the folder
//! of the typed path, folders first, then the files the editor opens or
//! writes. No native dialog: those need GTK or a desktop portal, which a
//! headless or lavapipe machine does not have.

use bevy_egui::egui;
use std::path::{Path, PathBuf};

/// File extensions the editor reads or writes (any case): fields, scripts
/// and compositions, masks and renders, splats and meshes.
const KINDS: [&str; 6] = ["safetensors", "ron", "json", "png", "ply", "glb"];

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Entry {
    pub name: String,
    pub path: PathBuf,
    pub is_dir: bool,
}

/// The folder a typed path points into: itself if it is a folder, else its
/// parent; the working directory for an empty path.
pub fn folder_of(typed: &str) -> PathBuf {
    let p = Path::new(typed.trim());
    if typed.trim().is_empty() {
        return PathBuf::from(".");
    }
    if p.is_dir() {
        return p.to_path_buf();
    }
    match p.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// Folders, then files with a known ending, each sorted by name; hidden
/// entries left out. An unreadable folder is an error naming it.
pub fn list(dir: &Path) -> std::io::Result<Vec<Entry>> {
    let mut out: Vec<Entry> = std::fs::read_dir(dir)?
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let is_dir = e.file_type().ok()?.is_dir();
            let wanted = is_dir || KINDS.contains(&crate::util::extension(Path::new(&name)).as_str());
            (wanted && !name.starts_with('.')).then(|| Entry {
                path: e.path(),
                name,
                is_dir,
            })
        })
        .collect();
    out.sort_by(|a, b| b.is_dir.cmp(&a.is_dir).then_with(|| a.name.cmp(&b.name)));
    Ok(out)
}

/// Draws the browser under a path field: a click on a folder enters it, a
/// click on a file puts its path into `typed`.
pub fn browser(ui: &mut egui::Ui, typed: &mut String) {
    let dir = folder_of(typed);
    ui.collapsing(format!("Browse {}", dir.display()), |ui| {
        if let Some(parent) = dir.canonicalize().ok().and_then(|d| d.parent().map(Path::to_path_buf)) {
            if ui.small_button("⬆ ..").clicked() {
                *typed = format!("{}/", parent.display());
            }
        }
        match list(&dir) {
            Err(e) => {
                ui.colored_label(egui::Color32::LIGHT_RED, format!("cannot read {}: {e}", dir.display()));
            }
            Ok(entries) => {
                egui::ScrollArea::vertical().max_height(220.0).show(ui, |ui| {
                    for e in entries {
                        let label = if e.is_dir {
                            format!("📁 {}/", e.name)
                        } else {
                            e.name.clone()
                        };
                        if ui.selectable_label(false, label).clicked() {
                            *typed = if e.is_dir {
                                format!("{}/", e.path.display())
                            } else {
                                e.path.display().to_string()
                            };
                        }
                    }
                });
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn folders_first_then_known_files_by_name() {
        let d = tempfile::tempdir().unwrap();
        for f in ["b.safetensors", "a.ron", "notes.txt", ".hidden.json", "c.png", "d.PLY"] {
            std::fs::write(d.path().join(f), b"x").unwrap();
        }
        std::fs::create_dir(d.path().join("zdir")).unwrap();
        std::fs::create_dir(d.path().join("adir")).unwrap();
        let names: Vec<String> = list(d.path()).unwrap().into_iter().map(|e| e.name).collect();
        assert_eq!(names, ["adir", "zdir", "a.ron", "b.safetensors", "c.png", "d.PLY"]);
        // A typed file points into its folder, a typed folder into itself.
        let typed = d.path().join("a.ron");
        assert_eq!(folder_of(&typed.display().to_string()), d.path());
        assert_eq!(folder_of(&d.path().display().to_string()), d.path());
        assert_eq!(folder_of("   "), PathBuf::from("."));
        assert_eq!(folder_of("new.ron"), PathBuf::from("."));
        assert!(list(&d.path().join("missing")).is_err());
    }
}
