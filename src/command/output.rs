//! Outputs: files written from a session (renders, mask / field / mesh /
//! bitmap exports, compositions, the edit log as a script). They read the
//! session and change nothing, so they live outside its state machine;
//! [`perform`] runs either kind of [`Command`].

use super::session::{Session, StepOutput};
use super::state::State;
use super::{CameraSource, Command, Export, Output};
use crate::camera::{Camera, CameraSet};
use crate::error::{Error, Result};
use crate::render::{render, save_png, to_rgb8, Probe, RenderOptions, Scene};
use crate::Result as R;
use glam::Vec3;
use std::sync::Arc;

/// Draws colour frames for `Render` outputs in place of the CPU reference
/// renderer (the editor's GPU ray marcher implements it for `isrf run --gpu`).
pub trait FrameRenderer {
    /// Colours in [0, 1], row-major, `camera`'s size.
    fn render_rgb(&mut self, scene: Arc<Scene>, camera: &Camera) -> Result<Vec<Vec3>>;
}

/// Applies an edit to the session, or writes an output from it.
pub fn perform(session: &mut Session, cmd: &Command, renderer: Option<&mut dyn FrameRenderer>) -> Result<StepOutput> {
    match cmd {
        Command::Edit(e) => session.apply(e),
        Command::Output(o) => write(session, o, renderer),
    }
}

/// Checks an output against the session as it stands, writing nothing:
/// what [`write`] checks before it writes (a script's dry run uses it).
pub fn check(session: &Session, out: &Output) -> Result<()> {
    let st = session.state();
    match out {
        Output::Render { cameras, downscale, .. } => {
            check_downscale(*downscale)?;
            self::cameras(session, cameras).map(drop)
        }
        Output::Export(Export::Masks {
            object,
            cameras,
            downscale,
            ..
        }) => {
            check_downscale(*downscale)?;
            self::cameras(session, cameras)?;
            mask_probe(st, object).map(drop)
        }
        Output::Export(
            Export::ObjectField { object, .. } | Export::Bitmap { object, .. } | Export::Splats { object, .. },
        ) => st.object_named(object).map(drop),
        Output::Export(Export::Mesh { target, out, iso }) => {
            if st.field_named(target).is_err() {
                st.object_named(target)?;
            }
            crate::edit::mesh::MeshFormat::of(out)?;
            crate::ensure_within!(
                OutOfRange,
                iso.is_none_or(|v| v.is_finite() && v > 0.0),
                "iso level must be positive"
            );
            Ok(())
        }
        Output::Export(Export::Composition { .. }) => Ok(()),
        Output::Export(Export::Script { out }) => super::script::Format::of(out).map(drop),
    }
}

fn check_downscale(downscale: u32) -> R<()> {
    crate::ensure_within!(OutOfRange, downscale >= 1, "downscale must be at least 1");
    Ok(())
}

/// Writes an output. Colour frames of `Render` are drawn by `renderer`
/// (e.g. the GPU ray marcher) when given, else by the CPU renderer.
pub fn write(session: &Session, out: &Output, renderer: Option<&mut dyn FrameRenderer>) -> Result<StepOutput> {
    let r = check(session, out).and_then(|_| match out {
        Output::Render { .. } => render_frames(session, out, renderer),
        Output::Export(e) => export(session, e),
    });
    session.progress.clear();
    let files = r?;
    Ok(StepOutput {
        message: format!("wrote {} files", files.len()),
        files,
        timings: None,
    })
}

/// Cameras of a camera source, in world coordinates.
pub fn cameras(session: &Session, src: &CameraSource) -> Result<CameraSet> {
    src.validate()?;
    match src {
        CameraSource::File(p) => CameraSet::load(&session.resolve(p)),
        CameraSource::Demo { field, eval } => {
            let f = session.field(field)?;
            let info = f
                .demo
                .as_ref()
                .ok_or_else(|| Error::invalid(format!("field '{field}' is not a demo scene: it has no cameras")))?;
            let mut set = if *eval {
                info.eval_cameras.clone()
            } else {
                info.cameras.clone()
            };
            for fr in &mut set.frames {
                fr.camera.c2w = f.placement.transform * fr.camera.c2w;
            }
            Ok(set)
        }
        CameraSource::Orbit { .. } => Ok(src.orbit_set().expect("orbit source")),
    }
}

fn render_frames(
    session: &Session,
    out: &Output,
    renderer: Option<&mut dyn FrameRenderer>,
) -> Result<Vec<std::path::PathBuf>> {
    let Output::Render {
        cameras,
        out: dir,
        downscale,
        frames,
        depth,
        background,
    } = out
    else {
        return Ok(vec![]);
    };
    let mut cams = self::cameras(session, cameras)?;
    if let Some(n) = frames {
        cams.frames.truncate(*n);
    }
    let mut scene = session.scene();
    if let Some(b) = background {
        scene.background = Vec3::from(*b);
    }
    let dir = session.output_path(dir);
    let opts = RenderOptions {
        depth: *depth,
        ..Default::default()
    };
    // Depth needs the CPU renderer's per-pixel outputs.
    let mut gpu = match renderer {
        Some(g) if !*depth => Some((g, Arc::new(scene.clone()))),
        _ => None,
    };
    let mut files = vec![];
    for (i, fr) in cams.frames.iter().enumerate() {
        session.progress.set("rendering", i as u64, cams.frames.len() as u64);
        let cam = fr.camera.downscaled(*downscale);
        let p = dir.join(format!("{}.png", fr.base_name()));
        if let Some((g, shared)) = gpu.as_mut() {
            let rgb = g.render_rgb(shared.clone(), &cam)?;
            save_png(&p, cam.intrinsics.width, cam.intrinsics.height, &to_rgb8(&rgb))?;
            files.push(p);
            continue;
        }
        let frame = render(&scene, &cam, &opts)?;
        save_png(&p, frame.width, frame.height, &to_rgb8(&frame.out.color))?;
        files.push(p);
        if *depth {
            let c = crate::render::colorize_depth(&frame.out.depth, &frame.out.opacity);
            let p = dir.join(format!("{}_depth.png", fr.base_name()));
            save_png(&p, frame.width, frame.height, &to_rgb8(&c))?;
            files.push(p);
        }
    }
    Ok(files)
}

/// The probe measuring an object's 2D mask: the layer `compose` put it in.
fn mask_probe(st: &State, object: &str) -> Result<(Scene, Probe)> {
    let o = st.object_named(object)?;
    let composed = st.compose();
    let probe = st
        .probe(&composed, o.id)
        .ok_or_else(|| Error::invalid(format!("object '{object}' is removed or hidden: it has no 2D mask")))?;
    Ok((composed.scene, probe))
}

fn export(session: &Session, e: &Export) -> Result<Vec<std::path::PathBuf>> {
    let st = session.state();
    let mut files = vec![];
    match e {
        Export::Masks {
            object,
            cameras,
            out: dir,
            downscale,
        } => {
            let cams = self::cameras(session, cameras)?;
            let (scene, probe) = mask_probe(st, object)?;
            let opts = RenderOptions {
                probes: vec![probe],
                depth: false,
                ..Default::default()
            };
            let dir = session.output_path(dir);
            for (i, fr) in cams.frames.iter().enumerate() {
                session
                    .progress
                    .set("exporting masks", i as u64, cams.frames.len() as u64);
                let f = render(&scene, &fr.camera.downscaled(*downscale), &opts)?;
                let m: Vec<u8> = f
                    .out
                    .probe_opacity
                    .iter()
                    .flat_map(|&v| [if v > 0.1 { 255 } else { 0 }; 3])
                    .collect();
                let p = dir.join(format!("{}_mask.png", fr.base_name()));
                save_png(&p, f.width, f.height, &m)?;
                files.push(p);
            }
        }
        Export::ObjectField {
            object,
            out: path,
            margin,
        } => {
            let o = st.object_named(object)?;
            let f = st.field_of(o)?;
            let cropped = crate::edit::crop::object_field(&f.field, &o.mask, *margin)?;
            let p = session.output_path(path);
            cropped.save(&p)?;
            files.push(p);
        }
        Export::Mesh { target, out: path, iso } => {
            session.progress.set("extracting the mesh", 0, 0);
            let p = session.output_path(path);
            export_mesh(st, target, *iso, &p)?;
            files.push(p);
        }
        Export::Bitmap { object, out: path } => {
            let o = st.object_named(object)?;
            let p = session.output_path(path);
            crate::segment::bitmap_file::save_bitmap(&p, &o.mask, &o.name)?;
            files.push(p);
        }
        Export::Composition { out: path } => {
            let p = session.output_path(path);
            files.extend(super::composition::save(session, &p)?);
        }
        Export::Splats {
            object,
            out: path,
            complement,
        } => {
            let (o, f) = (st.object_named(object)?, st.field_of(st.object_named(object)?)?);
            let p = session.output_path(path);
            let at = (o.placement.transform * f.placement.transform, o.placement.color_edit);
            crate::splat::export::export_object(&f.field, &o.mask, *complement, f.placement.transform, at, &p)?;
            files.push(p);
        }
        Export::Script { out: path } => {
            let p = session.output_path(path);
            let commands = session.log().iter().cloned().map(Command::Edit).collect();
            super::script::save_script(&super::Script { commands }, &p)?;
            files.push(p);
        }
    }
    Ok(files)
}

/// A mesh of a whole field or of an object, as placed in the composition.
fn export_mesh(st: &State, target: &str, iso: Option<f32>, path: &std::path::Path) -> Result<()> {
    use crate::edit::mesh::{field_mesh, MeshOptions};
    let mesh = if let Ok(f) = st.field_named(target) {
        let opts = MeshOptions {
            iso,
            object: None,
            transform: Some(f.placement.transform),
        };
        field_mesh(&f.field, &opts)?
    } else {
        let o = st.object_named(target)?;
        let f = st.field_of(o)?;
        let opts = MeshOptions {
            iso,
            object: Some(&o.mask),
            transform: Some(o.placement.transform * f.placement.transform),
        };
        field_mesh(&f.field, &opts)?
    };
    crate::edit::mesh::export_mesh(&mesh, path)
}
