//! Conversions between the library's maths types (glam 0.30) and bevy's
//! (glam 0.32), through plain arrays, plus camera helpers.

use crate::camera::{Camera, Intrinsics};
use bevy::camera::{PerspectiveProjection, Projection};
use bevy::math::{Mat4, Vec3};
use bevy::prelude::Transform;

pub fn to_bevy_vec3(v: glam::Vec3) -> Vec3 {
    Vec3::from_array(v.to_array())
}

pub fn from_bevy_vec3(v: Vec3) -> glam::Vec3 {
    glam::Vec3::from_array(v.to_array())
}

pub fn to_bevy_mat4(a: &glam::Affine3A) -> Mat4 {
    Mat4::from_cols_array(&glam::Mat4::from(*a).to_cols_array())
}

/// Library affine of a bevy transform (its full matrix, shear-free).
pub fn from_bevy_transform(t: &Transform) -> glam::Affine3A {
    let m = glam::Mat4::from_cols_array(&t.to_matrix().to_cols_array());
    glam::Affine3A::from_mat4(m)
}

/// A bevy transform equal to `a` when `a` has no shear (camera poses,
/// translate/rotate/scale edits).
pub fn bevy_transform(a: &glam::Affine3A) -> Transform {
    Transform::from_matrix(to_bevy_mat4(a))
}

/// A bevy perspective projection with the vertical field of view of `k`.
/// (The ray marcher takes exact intrinsics from `RayMarchCamera`; this only
/// sets the depth it writes and what meshes see.)
pub fn projection_for(k: &Intrinsics) -> Projection {
    let fov = 2.0 * (0.5 * k.height as f32 / k.fy).atan();
    Projection::Perspective(PerspectiveProjection {
        fov,
        aspect_ratio: k.width as f32 / k.height as f32,
        near: 0.01,
        ..Default::default()
    })
}

/// The library camera of a bevy camera pose and perspective projection at
/// the given image size (principal point at the centre, square pixels).
pub fn camera_from_bevy(t: &Transform, fov_y: f32, width: u32, height: u32) -> Camera {
    let fy = 0.5 * height as f32 / (0.5 * fov_y).tan();
    let k = Intrinsics {
        width,
        height,
        fx: fy,
        fy,
        cx: 0.5 * width as f32,
        cy: 0.5 * height as f32,
    };
    Camera::new(k, from_bevy_transform(t))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_round_trips_through_bevy() {
        let k = Intrinsics::from_fov_x(160, 120, 0.9);
        let c = Camera::look_at(k, glam::Vec3::new(1.0, 2.0, 3.0), glam::Vec3::ZERO, glam::Vec3::Y);
        let t = bevy_transform(&c.c2w);
        let Projection::Perspective(p) = projection_for(&k) else {
            unreachable!()
        };
        let back = camera_from_bevy(&t, p.fov, 160, 120);
        for (x, y) in [(0, 0), (80, 60), (159, 119)] {
            let (a, b) = (c.pixel_ray(x, y), back.pixel_ray(x, y));
            assert!((a.origin - b.origin).length() < 1e-5);
            assert!((a.dir - b.dir).length() < 1e-5, "pixel {x},{y}");
        }
    }
}
