//! Normalised device coordinates for forward-facing scenes (NeRF's
//! `ndc_rays`).
//!
//! The world must look roughly down −z (LLFF scenes after recentring). The
//! frustum of a reference pinhole (focal `focal`, image `width`×`height`)
//! from the plane z = −`near` to infinity maps to z_ndc ∈ [−1, 1), x and y to
//! [−1, 1] inside the reference field of view:
//!
//! ```text
//! x_ndc = −(2f/W)·x/z,  y_ndc = −(2f/H)·y/z,  z_ndc = 1 + 2·near/z
//! ```
//!
//! It is a projective map, so world rays are NDC rays. [`Ndc::ray`] does what
//! NeRF does (shift the origin to the near plane, then project) but returns a
//! unit direction: ray parameters are distances in NDC space, the field's
//! space for such scenes.

use super::Ray;
use crate::error::{Error, Result};
use glam::Vec3;
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Ndc {
    /// Near plane distance (z = −near in the world); NeRF uses 1.0.
    pub near: f32,
    /// Focal length in pixels of the reference image size below.
    pub focal: f32,
    pub width: u32,
    pub height: u32,
}

/// Directions with |d.z| below this are treated as grazing the near plane.
const MIN_DZ: f32 = 1e-6;

impl Ndc {
    /// NDC with NeRF's near plane at 1.0.
    pub fn new(focal: f32, width: u32, height: u32) -> Self {
        Ndc {
            near: 1.0,
            focal,
            width,
            height,
        }
    }
    /// Checks that the parameters define a usable mapping.
    pub fn validate(&self) -> Result<()> {
        let ok = self.near.is_finite()
            && self.near > 0.0
            && self.focal.is_finite()
            && self.focal > 0.0
            && self.width > 0
            && self.height > 0;
        if ok {
            Ok(())
        } else {
            Err(Error::invalid(format!(
                "bad NDC parameters (need near > 0, focal > 0, size > 0): {self:?}"
            )))
        }
    }
    /// The x and y scales 2f/W and 2f/H.
    pub fn scale(&self) -> (f32, f32) {
        (
            2.0 * self.focal / self.width as f32,
            2.0 * self.focal / self.height as f32,
        )
    }
    /// NDC point of a world point; `None` unless the point is in front of the
    /// z = 0 plane (z < 0).
    pub fn to_ndc(&self, p: Vec3) -> Option<Vec3> {
        if p.z >= -f32::EPSILON {
            return None;
        }
        let (sx, sy) = self.scale();
        Some(Vec3::new(-sx * p.x / p.z, -sy * p.y / p.z, 1.0 + 2.0 * self.near / p.z))
    }
    /// World point of an NDC point; `None` at or beyond z_ndc = 1 (infinity).
    pub fn to_world(&self, q: Vec3) -> Option<Vec3> {
        if q.z >= 1.0 - f32::EPSILON {
            return None;
        }
        let (sx, sy) = self.scale();
        let z = 2.0 * self.near / (q.z - 1.0);
        Some(Vec3::new(-q.x * z / sx, -q.y * z / sy, z))
    }
    /// The pinhole that defines this NDC space: at the origin, looking
    /// down −z, producing NDC rays.
    pub fn reference_camera(&self) -> super::Camera {
        let k = super::Intrinsics {
            width: self.width,
            height: self.height,
            fx: self.focal,
            fy: self.focal,
            cx: 0.5 * self.width as f32,
            cy: 0.5 * self.height as f32,
        };
        super::Camera::new(k, glam::Affine3A::IDENTITY).with_ndc(Some(*self))
    }
    /// The NDC ray of a world ray: origin moved along the ray to the near
    /// plane, then both projected (NeRF's `ndc_rays`), direction normalised.
    /// The ray starts at z_ndc = −1 and reaches z_ndc = 1 at world infinity.
    pub fn ray(&self, world: &Ray) -> Ray {
        // Forward-facing rays always have d.z < 0; clamp so that a grazing
        // ray still yields finite numbers instead of NaN.
        let d = world.dir;
        let dz = if d.z > -MIN_DZ { -MIN_DZ } else { d.z };
        let t = -(self.near + world.origin.z) / dz;
        let o = world.origin + t * Vec3::new(d.x, d.y, dz);
        let (sx, sy) = self.scale();
        let oz = -self.near;
        let origin = Vec3::new(-sx * o.x / oz, -sy * o.y / oz, -1.0);
        let dir = Vec3::new(
            -sx * (d.x / dz - o.x / oz),
            -sy * (d.y / dz - o.y / oz),
            -2.0 * self.near / oz,
        );
        Ray {
            origin,
            dir: dir.normalize(),
        }
    }
}
