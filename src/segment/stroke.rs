//! Strokes: pixels on a camera, stamped with a square brush, positive or
//! negative, for a named object. Read from JSON documents or NVOS-style
//! scribble PNGs; turned into unit-length rendered features.

use crate::camera::{Camera, CameraSet, Intrinsics};
use crate::ensure;
use crate::error::{Error, Result};
use crate::render::{render_rays, RenderOptions, Scene};
use glam::{Affine3A, Vec2};
use serde::{Deserialize, Serialize};
use std::path::Path;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Polarity {
    #[default]
    Positive,
    Negative,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Stroke {
    pub camera: Camera,
    /// Polyline in continuous pixel coordinates.
    pub points: Vec<Vec2>,
    /// Brush half-size in pixels: each point stamps a (2r+1)² square (the
    /// authors' tool uses r = 3, a 7×7 square).
    pub radius: u32,
    pub polarity: Polarity,
    pub object: String,
    /// Join consecutive points with line segments (a drawn polyline); false
    /// for scribble images, whose pixels are stamped individually.
    pub joined: bool,
}

/// Pixels covered by a stroke (deduplicated, row-major order), clipped to the
/// image. Consecutive points are joined so fast strokes stay continuous.
pub fn stroke_pixels(s: &Stroke) -> Result<Vec<(u32, u32)>> {
    ensure!(!s.points.is_empty(), "stroke for '{}' is empty (no points)", s.object);
    ensure!(
        s.points.iter().all(|p| p.is_finite()),
        "stroke for '{}' has a non-finite point",
        s.object
    );
    ensure!(s.radius <= 256, "brush radius {} is absurdly large (max 256)", s.radius);
    let (w, h) = (s.camera.intrinsics.width as i64, s.camera.intrinsics.height as i64);
    let mut hit = vec![false; (w * h) as usize];
    let r = s.radius as i64;
    // Coordinates are f64 and saturate when cast: a point 1e30 px away
    // stamps nothing instead of overflowing.
    let mut stamp = |x: f64, y: f64| {
        let (cx, cy) = (x.floor() as i64, y.floor() as i64);
        for y in cy.saturating_sub(r).max(0)..=cy.saturating_add(r).min(h - 1) {
            for x in cx.saturating_sub(r).max(0)..=cx.saturating_add(r).min(w - 1) {
                hit[(y * w + x) as usize] = true;
            }
        }
    };
    let at = |p: Vec2| (p.x as f64, p.y as f64);
    let (x0, y0) = at(s.points[0]);
    stamp(x0, y0);
    // The box a stamp centre must be in to touch the image.
    let reach = [
        -(r as f64) - 1.0,
        (w + r) as f64 + 1.0,
        -(r as f64) - 1.0,
        (h + r) as f64 + 1.0,
    ];
    for pair in s.points.windows(2) {
        if !s.joined {
            let (x, y) = at(pair[1]);
            stamp(x, y);
            continue;
        }
        // Only the part of the segment near the image is walked, one step
        // per pixel: its length is bounded by the image's, however far the
        // points lie.
        let (a, b) = (at(pair[0]), at(pair[1]));
        let Some((t0, t1)) = clip_segment(a, b, reach) else {
            continue;
        };
        let (dx, dy) = (b.0 - a.0, b.1 - a.1);
        let n = ((t1 - t0) * dx.hypot(dy)).ceil().max(1.0) as usize;
        for i in 0..=n {
            let t = t0 + (t1 - t0) * i as f64 / n as f64;
            stamp(a.0 + t * dx, a.1 + t * dy);
        }
    }
    let px: Vec<(u32, u32)> = (0..(w * h) as usize)
        .filter(|&i| hit[i])
        .map(|i| ((i as i64 % w) as u32, (i as i64 / w) as u32))
        .collect();
    ensure!(
        !px.is_empty(),
        "stroke for '{}' lies entirely off the {}x{} image",
        s.object,
        w,
        h
    );
    Ok(px)
}

/// The parameter interval `[t0, t1]` ⊆ [0, 1] of segment a→b inside the
/// box `[x_min, x_max, y_min, y_max]` (Liang–Barsky), `None` if it misses.
fn clip_segment(a: (f64, f64), b: (f64, f64), bx: [f64; 4]) -> Option<(f64, f64)> {
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, d, lo, hi) in [(a.0, b.0 - a.0, bx[0], bx[1]), (a.1, b.1 - a.1, bx[2], bx[3])] {
        if d == 0.0 {
            if p < lo || p > hi {
                return None;
            }
            continue;
        }
        let (ta, tb) = ((lo - p) / d, (hi - p) / d);
        t0 = t0.max(ta.min(tb));
        t1 = t1.min(ta.max(tb));
    }
    (t0 <= t1).then_some((t0, t1))
}

/// Rendered features at a stroke's pixels, each scaled to unit length
/// (`n × C`). Pixels whose rendered opacity is below `min_opacity` are on
/// empty space and are dropped; a stroke with none left is an error.
pub fn stroke_features(scene: &Scene, s: &Stroke, min_opacity: f32) -> Result<(Vec<f32>, usize)> {
    stroke_samples(scene, s, min_opacity).map(|x| (x.features, x.channels))
}

/// What a stroke's pixels see: their unit features and surface points.
pub struct StrokeSamples {
    /// `n × channels` unit features.
    pub features: Vec<f32>,
    pub channels: usize,
    /// The expected hit point of each kept pixel's ray (its depth over its
    /// opacity, in the space of the stroke camera's rays).
    pub hits: Vec<glam::Vec3>,
    /// The colour each kept pixel shows of the surface (its rendered colour
    /// less the background's share, over its opacity).
    pub colours: Vec<glam::Vec3>,
}

/// A stroke's rays stop once less than this share of their light is left
/// (renders go on to 10⁻⁴): what the stroke shows is its features'
/// weighted mean, which the last tenth of a percent does not move. A
/// grazing ray over a hazy floor shades a hundred faint samples past that
/// point, each reading 64 feature channels: the realistic tabletop's floor
/// stroke took 39–48 ms to read (26–37 ms now), its table 13–16 ms (6–9).
/// The benchmarks do not move beyond the third digit (`isrf bench
/// quality`: the floor, the table and the shelf each −0.001, the same
/// means; `isrf bench splats`: the same means; fern NVOS 0.8281 → 0.8292;
/// lego the same mask).
const STROKE_MIN_TRANSMITTANCE: f32 = 1e-3;

/// [`stroke_features`] with the surface points of the kept pixels.
pub fn stroke_samples(scene: &Scene, s: &Stroke, min_opacity: f32) -> Result<StrokeSamples> {
    let px = thinned(stroke_pixels(s)?, MAX_STROKE_SAMPLES);
    let rays: Vec<_> = px.iter().map(|&(x, y)| s.camera.pixel_ray(x, y)).collect();
    let opts = RenderOptions {
        features: true,
        depth: true,
        min_transmittance: STROKE_MIN_TRANSMITTANCE,
        ..Default::default()
    };
    let out = render_rays(scene, &rays, &opts)?;
    let c = out.feature_channels;
    ensure!(
        c > 0,
        "the scene has no semantic features: train or load a field with features to segment"
    );
    let mut feats = Vec::with_capacity(px.len() * c);
    let mut hits = Vec::with_capacity(px.len());
    let mut colours = Vec::with_capacity(px.len());
    for (i, &o) in out.opacity.iter().enumerate() {
        if o < min_opacity {
            continue;
        }
        let f = &out.features[i * c..(i + 1) * c];
        let n = f.iter().map(|x| x * x).sum::<f32>().sqrt();
        if n > 1e-12 {
            feats.extend(f.iter().map(|x| x / n));
            hits.push(rays[i].origin + rays[i].dir * (out.depth[i] / o));
            colours.push((out.color[i] - (1.0 - o) * scene.background) / o);
        }
    }
    ensure!(
        !feats.is_empty(),
        "stroke for '{}' lies on empty space ({} pixels, none hits the field)",
        s.object,
        px.len()
    );
    Ok(StrokeSamples {
        features: feats,
        channels: c,
        hits,
        colours,
    })
}

/// A stroke's pixels beyond this many are thinned to a regular sub-grid
/// before they are rendered (see [`thinned`]). Lego's stroke (2,169 pixels
/// → 542): features 50 → 12–19 ms, the alpha IoU the same (0.9919); fern
/// NVOS (2,783 → 696) 0.774 → 0.778; the realistic benchmark's 3D mean
/// 0.670 → 0.669 (its wall stroke: 0.583 → 0.574).
pub const MAX_STROKE_SAMPLES: usize = 1024;

/// `px` (image pixels) thinned when there are more than `cap`: the pixels
/// on every s-th row and column, s the smallest step that keeps no more
/// than `cap` of a filled area (a thin line along a row or column keeps
/// a 1/s share of its pixels). A wide brush's neighbouring pixels
/// see nearly the same features, a fraction of a voxel apart; rendering
/// each took a fifth of the lego stroke's time.
pub fn thinned(px: Vec<(u32, u32)>, cap: usize) -> Vec<(u32, u32)> {
    if px.len() <= cap || cap == 0 {
        return px;
    }
    let step = (px.len() as f64 / cap as f64).sqrt().ceil() as u32;
    let kept: Vec<(u32, u32)> = px
        .iter()
        .copied()
        .filter(|&(x, y)| x % step == 0 && y % step == 0)
        .collect();
    // A thin diagonal stroke may miss the sub-grid: keep every step²-th pixel.
    if kept.is_empty() {
        return px.into_iter().step_by((step * step) as usize).collect();
    }
    kept
}

// ------------------------------------------------------------ JSON documents

/// A camera in a stroke document: a transforms.json frame (`transform_matrix`
/// with `fl_x`/`fl_y`/`cx`/`cy`/`w`/`h` or `camera_angle_x`/`w`/`h`), or
/// `intrinsics` + `c2w` (4×4 row-major, OpenGL convention).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct CameraDoc {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file_path: Option<String>,
    /// 4×4 rows, or 3×4 as camera sets accept (bottom row [0 0 0 1]).
    #[serde(
        default,
        alias = "c2w",
        deserialize_with = "pose_rows",
        skip_serializing_if = "Option::is_none"
    )]
    pub transform_matrix: Option<[[f32; 4]; 4]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub intrinsics: Option<Intrinsics>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fl_x: Option<f32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fl_y: Option<f32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cx: Option<f32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cy: Option<f32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub w: Option<u32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub h: Option<u32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera_angle_x: Option<f32>,
    /// The NDC space of a forward-facing capture (as in camera sets), when
    /// the field was trained in it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ndc: Option<crate::camera::Ndc>,
}

/// A pose matrix's rows: 4, or 3 (the bottom row [0 0 0 1] implied), as
/// camera sets read `transform_matrix`; JSON arrays or RON tuples.
struct PoseRows([[f32; 4]; 4]);

impl<'de> Deserialize<'de> for PoseRows {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        struct V;
        impl<'de> serde::de::Visitor<'de> for V {
            type Value = PoseRows;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a 4×4 or 3×4 matrix (a list of rows of 4 numbers)")
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> std::result::Result<PoseRows, A::Error> {
                let mut m = [[0.0; 4]; 4];
                m[3] = [0.0, 0.0, 0.0, 1.0];
                let mut n = 0;
                while let Some(row) = seq.next_element::<[f32; 4]>()? {
                    if n == 4 {
                        return Err(serde::de::Error::invalid_length(5, &self));
                    }
                    m[n] = row;
                    n += 1;
                }
                if n < 3 {
                    return Err(serde::de::Error::invalid_length(n, &self));
                }
                Ok(PoseRows(m))
            }
        }
        d.deserialize_tuple(4, V)
    }
}

fn pose_rows<'de, D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Option<[[f32; 4]; 4]>, D::Error> {
    Ok(Option::<PoseRows>::deserialize(d)?.map(|p| p.0))
}

impl CameraDoc {
    pub fn from_camera(c: &Camera) -> Self {
        let k = c.intrinsics;
        CameraDoc {
            transform_matrix: Some(crate::camera::set::affine_to_rows(&c.c2w)),
            fl_x: Some(k.fx),
            fl_y: Some(k.fy),
            cx: Some(k.cx),
            cy: Some(k.cy),
            w: Some(k.width),
            h: Some(k.height),
            ndc: c.ndc,
            ..Default::default()
        }
    }
    /// The camera, parsed by the camera-set reader's rules (a rigid pose;
    /// intrinsics from `intrinsics` or the transforms.json keys).
    pub fn to_camera(&self) -> Result<Camera> {
        let fail = |why: String| Error::invalid(format!("stroke camera: {why}"));
        let m = self
            .transform_matrix
            .ok_or_else(|| fail("no transform_matrix / c2w".into()))?;
        let rows: Vec<Vec<f64>> = m.iter().map(|r| r.iter().map(|&v| f64::from(v)).collect()).collect();
        let c2w = crate::camera::set::rigid_from_rows(&rows).map_err(fail)?;
        let k = match self.intrinsics {
            Some(k) => {
                crate::camera::set::check_intrinsics(&k).map_err(fail)?;
                k
            }
            None => {
                let (Some(w), Some(h)) = (self.w, self.h) else {
                    return Err(fail("needs image size 'w' and 'h'".into()));
                };
                let keys = crate::camera::set::IntrinsicKeys {
                    fl_x: self.fl_x.map(f64::from),
                    fl_y: self.fl_y.map(f64::from),
                    cx: self.cx.map(f64::from),
                    cy: self.cy.map(f64::from),
                    camera_angle_x: self.camera_angle_x.map(f64::from),
                    camera_angle_y: None,
                };
                keys.intrinsics(w, h).map_err(fail)?
            }
        };
        if let Some(ndc) = &self.ndc {
            ndc.validate()?;
        }
        Ok(Camera::new(k, c2w).with_ndc(self.ndc))
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StrokeDoc {
    pub camera: CameraDoc,
    pub points: Vec<[f32; 2]>,
    #[serde(default = "default_radius")]
    pub radius: u32,
    #[serde(default)]
    pub polarity: Polarity,
    #[serde(default = "default_object")]
    pub object: String,
}

fn default_radius() -> u32 {
    3
}
fn default_object() -> String {
    "object".into()
}

impl StrokeDoc {
    pub fn from_stroke(s: &Stroke) -> Self {
        StrokeDoc {
            camera: CameraDoc::from_camera(&s.camera),
            points: s.points.iter().map(|p| p.to_array()).collect(),
            radius: s.radius,
            polarity: s.polarity,
            object: s.object.clone(),
        }
    }
    pub fn to_stroke(&self) -> Result<Stroke> {
        self.to_stroke_on(self.camera.to_camera()?)
    }

    /// The stroke drawn on `camera` (the document's own camera ignored).
    pub fn to_stroke_on(&self, camera: Camera) -> Result<Stroke> {
        Ok(Stroke {
            camera,
            points: self.points.iter().map(|&p| Vec2::from(p)).collect(),
            radius: self.radius,
            polarity: self.polarity,
            object: self.object.clone(),
            joined: true,
        })
    }
}

/// Reads strokes from a JSON file; every error names the file (and stroke).
pub fn load_strokes(path: &Path) -> Result<Vec<Stroke>> {
    load_strokes_on(path, None)
}

/// Like [`load_strokes`]; a stroke whose camera is only a `file_path` takes
/// that frame's camera from `cameras` (e.g. a dataset's camera set).
pub fn load_strokes_on(path: &Path, cameras: Option<&CameraSet>) -> Result<Vec<Stroke>> {
    load_strokes_in(path, cameras, Affine3A::IDENTITY)
}

/// Like [`load_strokes_on`] for cameras given in a field's frame: the views
/// taken from `cameras` are moved by `to_world` (where the field is placed);
/// cameras spelt out in the file are world cameras already.
pub fn load_strokes_in(path: &Path, cameras: Option<&CameraSet>, to_world: Affine3A) -> Result<Vec<Stroke>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    parse_strokes_in(&text, cameras, to_world).map_err(|e| Error::bad_file(path, e.to_string()))
}

pub fn parse_strokes(text: &str) -> Result<Vec<Stroke>> {
    parse_strokes_on(text, None)
}

/// The stroke documents of a stroke file's text (at least one). A file
/// holds one stroke, a list, or `{ "strokes": [...] }`: the JSON is parsed
/// first and its shape decides which, so an error inside a list names the
/// stroke and the real problem (not "expected a single stroke").
fn stroke_docs(text: &str) -> Result<Vec<StrokeDoc>> {
    use serde_json::Value;
    let value: Value =
        serde_json::from_str(text).map_err(|e| Error::invalid(format!("not a stroke document: invalid JSON: {e}")))?;
    let one = |i: Option<usize>, v: Value| {
        StrokeDoc::deserialize(v).map_err(|e| match i {
            Some(i) => Error::invalid(format!("stroke {i}: {e}")),
            None => Error::invalid(format!("not a stroke document: {e}")),
        })
    };
    let list = |items: Vec<Value>| -> Result<Vec<StrokeDoc>> {
        items.into_iter().enumerate().map(|(i, v)| one(Some(i), v)).collect()
    };
    let docs = match value {
        Value::Array(items) => list(items)?,
        Value::Object(mut m) if m.contains_key("strokes") => match m.remove("strokes") {
            Some(Value::Array(items)) => list(items)?,
            _ => return Err(Error::invalid("'strokes' must be a list of strokes")),
        },
        v @ Value::Object(_) => vec![one(None, v)?],
        _ => {
            return Err(Error::invalid(
                "not a stroke document: expected a stroke, a list of strokes or {\"strokes\": [...]}",
            ))
        }
    };
    ensure!(!docs.is_empty(), "the stroke document holds no strokes");
    Ok(docs)
}

pub fn parse_strokes_on(text: &str, cameras: Option<&CameraSet>) -> Result<Vec<Stroke>> {
    parse_strokes_in(text, cameras, Affine3A::IDENTITY)
}

fn parse_strokes_in(text: &str, cameras: Option<&CameraSet>, to_world: Affine3A) -> Result<Vec<Stroke>> {
    let docs = stroke_docs(text)?;
    docs.iter()
        .enumerate()
        .map(|(i, d)| {
            let named = d.camera.transform_matrix.is_none() && d.camera.file_path.is_some();
            let stroke = match (named, cameras) {
                (true, Some(set)) => {
                    let mut camera = frame_camera(set, &d.camera)?;
                    camera.c2w = to_world * camera.c2w;
                    d.to_stroke_on(camera)
                }
                _ => d.to_stroke(),
            };
            stroke.map_err(|e| Error::invalid(format!("stroke {i}: {e}")))
        })
        .collect()
}

/// The camera of the frame of `set` that `doc.file_path` names (full name
/// or base name); the document's `w`/`h`, if given, must match it.
fn frame_camera(set: &CameraSet, doc: &CameraDoc) -> Result<Camera> {
    let want = doc.file_path.as_deref().unwrap_or_default();
    let base = |n: &str| {
        let n = n.rsplit('/').next().unwrap_or(n);
        n.rsplit_once('.').map_or(n, |(b, _)| b).to_string()
    };
    let frame = set
        .frames
        .iter()
        .find(|f| f.name == want || f.base_name() == base(want))
        .ok_or_else(|| {
            let names: Vec<String> = set.frames.iter().take(6).map(|f| f.base_name()).collect();
            Error::invalid(format!(
                "no camera named '{want}' in the camera set (it has {}, ...)",
                names.join(", ")
            ))
        })?;
    let k = frame.camera.intrinsics;
    let (Some(w), Some(h)) = (doc.w, doc.h) else {
        return Ok(frame.camera);
    };
    // A stroke drawn on a downscaled copy of the image (e.g. training at
    // --downscale 4 against the dataset's own transforms file).
    let factor = if w > 0 { k.width / w } else { 0 };
    ensure!(
        factor >= 1 && k.width == w * factor && frame.camera.downscaled(factor).intrinsics.height == h,
        "stroke is drawn on a {w}x{h} image but camera '{want}' is {}x{} (not an integer multiple)",
        k.width,
        k.height
    );
    Ok(frame.camera.downscaled(factor))
}

/// A scribble PNG (NVOS style: any non-zero pixel is stroked) on `camera`.
/// The image must have the camera's size.
pub fn scribble_stroke(path: &Path, camera: Camera, polarity: Polarity, object: &str) -> Result<Stroke> {
    let k = camera.intrinsics;
    // The size is checked from the header before decoding.
    let img = crate::data::open_image(path, Some((k.width, k.height)))?.to_luma8();
    let points: Vec<Vec2> = img
        .enumerate_pixels()
        .filter(|(_, _, p)| p.0[0] > 0)
        .map(|(x, y, _)| Vec2::new(x as f32 + 0.5, y as f32 + 0.5))
        .collect();
    ensure!(
        !points.is_empty(),
        "scribble {} has no stroked (non-zero) pixels",
        path.display()
    );
    // Scribble pixels are stamped individually (no joining of far-apart pixels).
    Ok(Stroke {
        camera,
        points,
        radius: 0,
        polarity,
        object: object.into(),
        joined: false,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn stroke_cameras_parse_like_camera_set_frames() {
        let m = "[[0.0, 0.0, 1.0, 2.0], [0.0, 1.0, 0.0, 0.5], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]";
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("transforms.json");
        let set = format!(
            r#"{{"camera_angle_x": 0.7, "w": 64, "h": 48, "frames": [{{"file_path": "a", "transform_matrix": {m}}}]}}"#
        );
        std::fs::write(&path, set).unwrap();
        let from_set = CameraSet::load(&path).unwrap().frames[0].camera;
        let doc: CameraDoc = serde_json::from_str(&format!(
            r#"{{"camera_angle_x": 0.7, "w": 64, "h": 48, "transform_matrix": {m}}}"#
        ))
        .unwrap();
        let from_doc = doc.to_camera().unwrap();
        assert_eq!(from_doc.intrinsics, from_set.intrinsics);
        assert_eq!(from_doc.c2w, from_set.c2w);
        // The same rules refuse the same poses: a scaled matrix is not a camera.
        let mut scaled = doc.clone();
        scaled.transform_matrix.as_mut().unwrap()[0][2] = 2.0;
        let e = scaled.to_camera().unwrap_err().to_string();
        assert!(
            e.starts_with("stroke camera: ") && e.contains("not a rigid transform"),
            "{e}"
        );
        let mut huge = doc.clone();
        huge.w = Some(1 << 20);
        assert!(huge.to_camera().unwrap_err().to_string().contains("bad image size"));
        // A 3×4 matrix, which camera sets accept, is the same camera.
        let m34 = "[[0.0, 0.0, 1.0, 2.0], [0.0, 1.0, 0.0, 0.5], [-1.0, 0.0, 0.0, 0.0]]";
        let doc34: CameraDoc = serde_json::from_str(&format!(
            r#"{{"camera_angle_x": 0.7, "w": 64, "h": 48, "transform_matrix": {m34}}}"#
        ))
        .unwrap();
        assert_eq!(doc34.transform_matrix, doc.transform_matrix);
        // In RON scripts too, as tuples; 2 or 5 rows are refused.
        let ron34 = "(camera_angle_x: Some(0.7), w: Some(64), h: Some(48), transform_matrix: Some(((0, 0, 1, 2), (0, 1, 0, 0.5), (-1, 0, 0, 0))))";
        let r: CameraDoc = ron::from_str(ron34).unwrap();
        assert_eq!(r.transform_matrix, doc.transform_matrix);
        for rows in [
            "[[1,0,0,0],[0,1,0,0]]",
            "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1],[0,0,0,1]]",
        ] {
            let e = serde_json::from_str::<CameraDoc>(&format!(r#"{{"transform_matrix": {rows}}}"#)).unwrap_err();
            assert!(e.to_string().contains("4×4 or 3×4"), "{e}");
        }
    }

    fn stroke(points: &[[f32; 2]], radius: u32, w: u32, h: u32) -> Stroke {
        Stroke {
            camera: Camera::look_at(Intrinsics::from_fov_x(w, h, 0.8), Vec3::Z * 3.0, Vec3::ZERO, Vec3::Y),
            points: points.iter().map(|&p| Vec2::from(p)).collect(),
            radius,
            polarity: Polarity::Positive,
            object: "o".into(),
            joined: true,
        }
    }

    #[test]
    fn a_segment_from_far_away_covers_what_it_crosses() {
        // Row 2 from far left to far right, brush radius 1: rows 1..=3.
        let want: Vec<(u32, u32)> = (1..=3).flat_map(|y| (0..8).map(move |x| (x, y))).collect();
        for far in [100.0, 1e6, 1e9] {
            let s = stroke(&[[-far, 2.5], [far, 2.5]], 1, 8, 8);
            assert_eq!(stroke_pixels(&s).unwrap(), want, "endpoints at ±{far}");
        }
        // A diagonal through the whole image from far outside.
        let s = stroke(&[[-1e5, -1e5], [1e5, 1e5]], 0, 6, 6);
        assert_eq!(stroke_pixels(&s).unwrap(), (0..6).map(|i| (i, i)).collect::<Vec<_>>());
        // Beyond what f64 resolves at the image, the walk still ends at
        // once with pixels on the image (one step, not 1e30).
        for far in [1e12, 1e30, f32::MAX] {
            let s = stroke(&[[-far, 2.5], [far, 2.5]], 1, 8, 8);
            let px = stroke_pixels(&s).unwrap();
            assert!(px.iter().all(|&(x, y)| x < 8 && (1..=3).contains(&y)), "±{far}: {px:?}");
        }
    }

    #[test]
    fn points_far_off_the_image_are_an_error_not_a_panic() {
        for p in [[1e30, 0.0], [-1e30, 0.0], [0.0, 1e30], [0.0, -f32::MAX]] {
            let s = stroke(&[p], 3, 4, 4);
            let e = stroke_pixels(&s).unwrap_err().to_string();
            assert!(e.contains("off the 4x4 image"), "{p:?}: {e}");
        }
        // A segment passing beside the image stamps nothing either.
        let s = stroke(&[[-1e12, -50.0], [1e12, -50.0]], 3, 4, 4);
        assert!(stroke_pixels(&s).is_err());
    }

    #[test]
    fn clipping_keeps_the_part_inside_the_box() {
        let b = [0.0, 10.0, 0.0, 10.0];
        assert_eq!(clip_segment((-10.0, 5.0), (30.0, 5.0), b), Some((0.25, 0.5)));
        assert_eq!(clip_segment((2.0, 2.0), (3.0, 3.0), b), Some((0.0, 1.0)));
        assert_eq!(clip_segment((-5.0, 20.0), (15.0, 20.0), b), None);
        assert_eq!(clip_segment((5.0, -1.0), (5.0, -1.0), b), None);
    }

    #[test]
    fn wide_strokes_are_thinned_to_a_regular_sub_grid() {
        // A wide brush: a 60×40 block of pixels.
        let block: Vec<(u32, u32)> = (0..40).flat_map(|y| (0..60).map(move |x| (x, y))).collect();
        assert_eq!(thinned(block.clone(), 2400), block, "within the cap: untouched");
        let thin = thinned(block.clone(), 1000);
        // Every second row and column: a quarter, spread over the block.
        assert_eq!(thin.len(), 600);
        assert!(thin.iter().all(|&(x, y)| x % 2 == 0 && y % 2 == 0));
        assert_eq!((thin[0], *thin.last().unwrap()), ((0, 0), (58, 38)));
        let thin = thinned(block, 100);
        assert!(thin.len() <= 100 && thin.len() >= 40, "{}", thin.len());
        // A one-pixel diagonal line off the sub-grid still keeps pixels.
        let diagonal: Vec<(u32, u32)> = (0..2000).map(|i| (2 * i + 1, 2 * i)).collect();
        let thin = thinned(diagonal.clone(), 1000);
        assert!(!thin.is_empty() && thin.len() <= 1000);
        assert!(thin.iter().all(|p| diagonal.contains(p)));
    }
}
