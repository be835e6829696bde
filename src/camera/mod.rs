//! Pinhole cameras and rays.
//!
//! Convention (as NeRF/Blender/OpenGL): camera-to-world `c2w`, the camera looks
//! down its −z axis with +y up and +x right. Pixel (u, v) has its centre at
//! (u + 0.5, v + 0.5), v grows downwards. OpenCV (x right, y down, +z forward)
//! poses convert with [`Camera::from_opencv`] / [`Camera::c2w_opencv`].
//! Rays carry a unit direction, so ray parameters `t` are world distances.
//!
//! Forward-facing captures (LLFF) are usually reconstructed in normalised
//! device coordinates: a camera with [`Camera::ndc`] set produces rays in NDC
//! space (see [`Ndc`]), which is then the field's space.

pub mod colmap;
pub mod llff;
mod ndc;
pub mod set;
pub use ndc::Ndc;
pub use set::{CameraFrame, CameraSet};

use glam::{Affine3A, Vec2, Vec3};
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
}

impl Intrinsics {
    /// Square pixels, principal point at the centre, horizontal field of view.
    pub fn from_fov_x(width: u32, height: u32, fov_x: f32) -> Self {
        let f = 0.5 * width as f32 / (0.5 * fov_x).tan();
        Intrinsics {
            width,
            height,
            fx: f,
            fy: f,
            cx: 0.5 * width as f32,
            cy: 0.5 * height as f32,
        }
    }
    /// The same camera at 1/`factor` resolution.
    pub fn downscaled(&self, factor: u32) -> Self {
        let s = 1.0 / factor.max(1) as f32;
        Intrinsics {
            width: (self.width / factor.max(1)).max(1),
            height: (self.height / factor.max(1)).max(1),
            fx: self.fx * s,
            fy: self.fy * s,
            cx: self.cx * s,
            cy: self.cy * s,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub origin: Vec3,
    /// Unit length.
    pub dir: Vec3,
}

impl Ray {
    pub fn at(&self, t: f32) -> Vec3 {
        self.origin + t * self.dir
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    pub intrinsics: Intrinsics,
    /// Camera-to-world, OpenGL convention.
    pub c2w: Affine3A,
    /// When set, rays and projections live in this NDC space instead of the
    /// world (forward-facing scenes); `c2w` stays the world pose.
    pub ndc: Option<Ndc>,
}

/// Flips y and z: converts between the OpenGL and OpenCV camera frames.
fn flip_yz() -> Affine3A {
    Affine3A::from_mat3(glam::Mat3::from_diagonal(Vec3::new(1.0, -1.0, -1.0)))
}

impl Camera {
    pub fn new(intrinsics: Intrinsics, c2w: Affine3A) -> Self {
        Camera {
            intrinsics,
            c2w,
            ndc: None,
        }
    }
    /// The same camera producing rays in NDC space `ndc` (or in the world).
    pub fn with_ndc(self, ndc: Option<Ndc>) -> Self {
        Camera { ndc, ..self }
    }
    /// A camera at `eye` looking at `target` with `up` roughly up.
    pub fn look_at(intrinsics: Intrinsics, eye: Vec3, target: Vec3, up: Vec3) -> Self {
        let back = (eye - target).normalize();
        let right = up.cross(back).normalize();
        let up = back.cross(right);
        let c2w = Affine3A::from_mat3_translation(glam::Mat3::from_cols(right, up, back), eye);
        Camera::new(intrinsics, c2w)
    }
    /// From an OpenCV camera-to-world pose (x right, y down, z forward).
    pub fn from_opencv(intrinsics: Intrinsics, c2w_cv: Affine3A) -> Self {
        Camera::new(intrinsics, c2w_cv * flip_yz())
    }
    /// This pose in the OpenCV convention.
    pub fn c2w_opencv(&self) -> Affine3A {
        self.c2w * flip_yz()
    }
    pub fn position(&self) -> Vec3 {
        self.c2w.translation.into()
    }
    /// Unit up direction of the image (camera +y in world).
    pub fn up(&self) -> Vec3 {
        Vec3::from(self.c2w.matrix3.y_axis).normalize_or_zero()
    }
    /// Unit viewing direction (camera −z in world).
    pub fn forward(&self) -> Vec3 {
        -Vec3::from(self.c2w.matrix3.z_axis).normalize()
    }
    /// Ray through continuous pixel coordinates (pixel centres at +0.5), in
    /// the world, or in NDC space when [`Camera::ndc`] is set (then it starts
    /// on the near plane; see [`Ndc::ray`]).
    pub fn ray(&self, u: f32, v: f32) -> Ray {
        let world = self.world_ray(u, v);
        match &self.ndc {
            Some(ndc) => ndc.ray(&world),
            None => world,
        }
    }
    /// World-space ray through continuous pixel coordinates, ignoring NDC.
    pub fn world_ray(&self, u: f32, v: f32) -> Ray {
        let k = &self.intrinsics;
        let d_cam = Vec3::new((u - k.cx) / k.fx, -(v - k.cy) / k.fy, -1.0);
        let dir = (self.c2w.matrix3 * d_cam).normalize();
        Ray {
            origin: self.position(),
            dir,
        }
    }
    /// Ray through the centre of pixel (x, y).
    pub fn pixel_ray(&self, x: u32, y: u32) -> Ray {
        self.ray(x as f32 + 0.5, y as f32 + 0.5)
    }
    /// Continuous pixel coordinates of a point and its depth along −z;
    /// `None` behind the camera. The point is in the camera's ray space: with
    /// [`Camera::ndc`] set it is an NDC point, mapped back to the world first
    /// (`None` at or beyond NDC z = 1, the plane at infinity); the depth is
    /// always the world-space depth.
    pub fn project(&self, p: Vec3) -> Option<(Vec2, f32)> {
        let p = match &self.ndc {
            Some(ndc) => ndc.to_world(p)?,
            None => p,
        };
        self.project_world(p)
    }
    /// [`Camera::project`] of a world point, ignoring NDC.
    pub fn project_world(&self, p: Vec3) -> Option<(Vec2, f32)> {
        let q = self.c2w.inverse().transform_point3(p);
        let z = -q.z;
        if z <= 1e-6 {
            return None;
        }
        let k = &self.intrinsics;
        Some((Vec2::new(k.fx * q.x / z + k.cx, -k.fy * q.y / z + k.cy), z))
    }
    /// The same camera at 1/`factor` resolution. The NDC space, if any, is
    /// unchanged (it is the field's space, shared by every resolution).
    pub fn downscaled(&self, factor: u32) -> Self {
        Camera {
            intrinsics: self.intrinsics.downscaled(factor),
            ..*self
        }
    }
}

/// The cameras' shared up direction, in the space of the field trained
/// from them (NDC for forward-facing captures), if they agree on one: the
/// mean of their image-up directions when it is at least [`UPRIGHT`] long
/// (people hold cameras upright; orbits that look down on a scene tilt
/// each camera's up by their elevation, and a mean of unit vectors that
/// point every which way is short).
pub fn up_of(cameras: &[Camera]) -> Option<Vec3> {
    let sum: Vec3 = cameras.iter().map(Camera::up).sum();
    let mean = sum / cameras.len().max(1) as f32;
    if !mean.is_finite() || mean.length() < UPRIGHT {
        return None;
    }
    let up = mean.normalize();
    match cameras.iter().find_map(|c| c.ndc) {
        // The NDC map is projective: a direction maps at a point, here
        // one in front of the reference camera.
        Some(ndc) => {
            let at = Vec3::new(0.0, 0.0, -2.0 * ndc.near);
            let d = ndc.to_ndc(at + 0.01 * up)? - ndc.to_ndc(at)?;
            d.try_normalize()
        }
        None => Some(up),
    }
}

/// The least length of the mean image-up direction for the cameras to
/// agree on one ([`up_of`]): an orbit at 60° elevation gives 0.5.
pub const UPRIGHT: f32 = 0.45;
