//! `isrf render`: one PNG per camera frame (colour, optionally depth,
//! features and object masks).

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use isrf::camera::CameraSet;
use isrf::field::Field;
use isrf::render::{colorize_depth, features_to_rgb, render, save_png, to_rgb8, Layer, Probe, RenderOptions, Scene};
use isrf::segment::bitmap_file::load_bitmap;
use std::path::PathBuf;
use std::sync::Arc;

#[derive(clap::Args)]
pub struct Args {
    /// Field files (.safetensors), composited together.
    #[arg(required = true)]
    pub fields: Vec<PathBuf>,
    /// Camera set (transforms.json).
    #[arg(long)]
    pub cameras: PathBuf,
    /// Output folder; frames are named after each frame's file_path base name.
    #[arg(long)]
    pub out: PathBuf,
    /// Render at 1/N of the cameras' resolution.
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    /// Also write <name>_depth.png (colour-mapped expected depth).
    #[arg(long)]
    pub depth: bool,
    /// Also write <name>_features.png (features projected to RGB by PCA).
    #[arg(long)]
    pub features: bool,
    /// Object bitmap of the first field (from `isrf segment`).
    #[arg(long)]
    pub object: Option<PathBuf>,
    /// With --object: also write <name>_mask.png, the object's opacity > 0.1.
    #[arg(long, requires = "object")]
    pub mask: bool,
    /// Render only the first N frames.
    #[arg(long)]
    pub frames: Option<usize>,
    /// Draw VM + MLP appearance through the per-voxel SH fit the editor's
    /// GPU view uses (to see what the editor shows).
    #[arg(long)]
    pub baked_sh: bool,
    /// Background colour, e.g. 1,1,1 (white, the default) or 0,0,0.
    #[arg(long, default_value = "1,1,1", value_parser = parse_rgb)]
    pub background: glam::Vec3,
}

pub fn parse_rgb(s: &str) -> Result<glam::Vec3, String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|x| x.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("'{s}': {e}"))?;
    match v[..] {
        [r, g, b] if v.iter().all(|x| x.is_finite() && (0.0..=1.0).contains(x)) => Ok(glam::Vec3::new(r, g, b)),
        _ => Err(format!("'{s}' is not three numbers in [0, 1] separated by commas")),
    }
}

pub fn run(a: Args) -> Result<()> {
    if a.downscale == 0 {
        bail!("--downscale must be at least 1");
    }
    let mut layers = vec![];
    for p in &a.fields {
        let mut field = Arc::new(Field::load(p)?);
        if a.baked_sh {
            if let Some(baked) = field.sh_baked()? {
                field = baked;
            }
        }
        layers.push(Layer::new(field));
    }
    let mut probes = vec![];
    if let Some(path) = &a.object {
        let (bits, _) = load_bitmap(path)?;
        let res = layers[0].field.res();
        if bits.res() != res {
            bail!(
                "{}: bitmap resolution {:?} does not match {} ({res:?})",
                path.display(),
                bits.res(),
                a.fields[0].display()
            );
        }
        probes.push(Probe {
            layer: 0,
            mask: Arc::new(bits),
        });
    }
    let mut scene = Scene::new(layers);
    scene.background = a.background;
    let mut cams = CameraSet::load(&a.cameras)?;
    if let Some(n) = a.frames {
        cams.frames.truncate(n);
    }
    if cams.frames.is_empty() {
        bail!("{}: no frames to render", a.cameras.display());
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let opts = RenderOptions {
        features: a.features,
        probes,
        ..Default::default()
    };
    let bar = ProgressBar::new(cams.frames.len() as u64);
    bar.set_style(ProgressStyle::with_template("{bar:40} {pos}/{len} frames  {elapsed} (eta {eta}) {msg}").unwrap());
    for f in &cams.frames {
        let cam = f.camera.downscaled(a.downscale);
        let frame = render(&scene, &cam, &opts)?;
        let (w, h, o) = (frame.width, frame.height, &frame.out);
        let name = f.base_name();
        save_png(&a.out.join(format!("{name}.png")), w, h, &to_rgb8(&o.color))?;
        if a.depth {
            save_png(
                &a.out.join(format!("{name}_depth.png")),
                w,
                h,
                &to_rgb8(&colorize_depth(&o.depth, &o.opacity)),
            )?;
        }
        if a.features {
            let rgb = features_to_rgb(&o.features, o.feature_channels, &o.opacity);
            save_png(&a.out.join(format!("{name}_features.png")), w, h, &to_rgb8(&rgb))?;
        }
        if a.mask {
            let m: Vec<u8> = o
                .probe_opacity
                .iter()
                .flat_map(|&v| [if v > 0.1 { 255 } else { 0 }; 3])
                .collect();
            save_png(&a.out.join(format!("{name}_mask.png")), w, h, &m)?;
        }
        bar.inc(1);
    }
    bar.finish_with_message(format!("written to {}", a.out.display()));
    Ok(())
}
