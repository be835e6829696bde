//! Signed distance functions for the procedural scenes (the classic formulas
//! collected by Inigo Quilez). Distances are in world units, negative inside.
//! The approximate ones (ellipsoid, subtraction, intersection) are accurate
//! near the surface, which is all the voxeliser needs: density only depends
//! on the distance within a voxel or two of the boundary.

use crate::field::Aabb;
use glam::{Affine3A, Quat, Vec2, Vec3};

#[derive(Clone, Debug)]
pub enum Sdf {
    /// Box with outer half extents `half`, edges rounded by `round`.
    Cuboid {
        half: Vec3,
        round: f32,
    },
    /// Cylinder along y, centred at the origin.
    Cylinder {
        radius: f32,
        half_height: f32,
    },
    /// Frustum along y: radius `bottom` at y = −h, `top` at y = +h.
    Cone {
        bottom: f32,
        top: f32,
        half_height: f32,
    },
    Sphere {
        radius: f32,
    },
    Ellipsoid {
        radii: Vec3,
    },
    /// Segment `a`–`b` thickened by `radius`.
    Capsule {
        a: Vec3,
        b: Vec3,
        radius: f32,
    },
    /// Torus around the y axis.
    Torus {
        major: f32,
        minor: f32,
    },
    /// `inner` placed by a rigid transform; `to_local` maps world → local.
    Placed {
        to_local: Affine3A,
        inner: Box<Sdf>,
    },
    /// First minus second.
    Subtract(Box<Sdf>, Box<Sdf>),
    Intersect(Box<Sdf>, Box<Sdf>),
}

impl Sdf {
    pub fn cuboid(half: Vec3, round: f32) -> Sdf {
        Sdf::Cuboid { half, round }
    }
    pub fn cylinder(radius: f32, half_height: f32) -> Sdf {
        Sdf::Cylinder { radius, half_height }
    }
    pub fn cone(bottom: f32, top: f32, half_height: f32) -> Sdf {
        Sdf::Cone {
            bottom,
            top,
            half_height,
        }
    }
    pub fn sphere(radius: f32) -> Sdf {
        Sdf::Sphere { radius }
    }
    pub fn ellipsoid(radii: Vec3) -> Sdf {
        Sdf::Ellipsoid { radii }
    }
    pub fn capsule(a: Vec3, b: Vec3, radius: f32) -> Sdf {
        Sdf::Capsule { a, b, radius }
    }
    pub fn torus(major: f32, minor: f32) -> Sdf {
        Sdf::Torus { major, minor }
    }
    /// This shape rotated by `rot`, then moved to `pos`.
    pub fn place(self, pos: Vec3, rot: Quat) -> Sdf {
        Sdf::Placed {
            to_local: Affine3A::from_rotation_translation(rot, pos).inverse(),
            inner: Box::new(self),
        }
    }
    pub fn at(self, pos: Vec3) -> Sdf {
        self.place(pos, Quat::IDENTITY)
    }
    pub fn minus(self, other: Sdf) -> Sdf {
        Sdf::Subtract(Box::new(self), Box::new(other))
    }
    pub fn and(self, other: Sdf) -> Sdf {
        Sdf::Intersect(Box::new(self), Box::new(other))
    }

    /// Signed distance at `p`.
    pub fn dist(&self, p: Vec3) -> f32 {
        match self {
            Sdf::Cuboid { half, round } => {
                let q = p.abs() - *half + Vec3::splat(*round);
                q.max(Vec3::ZERO).length() + q.max_element().min(0.0) - round
            }
            Sdf::Cylinder { radius, half_height } => {
                let d = Vec2::new(Vec2::new(p.x, p.z).length(), p.y).abs() - Vec2::new(*radius, *half_height);
                d.max_element().min(0.0) + d.max(Vec2::ZERO).length()
            }
            Sdf::Cone {
                bottom,
                top,
                half_height,
            } => cone(p, *bottom, *top, *half_height),
            Sdf::Sphere { radius } => p.length() - radius,
            Sdf::Ellipsoid { radii } => {
                let k0 = (p / *radii).length();
                let k1 = (p / (*radii * *radii)).length();
                if k1 < 1e-12 {
                    -radii.min_element()
                } else {
                    k0 * (k0 - 1.0) / k1
                }
            }
            Sdf::Capsule { a, b, radius } => {
                let (pa, ba) = (p - *a, *b - *a);
                let h = (pa.dot(ba) / ba.length_squared().max(1e-12)).clamp(0.0, 1.0);
                (pa - ba * h).length() - radius
            }
            Sdf::Torus { major, minor } => Vec2::new(Vec2::new(p.x, p.z).length() - major, p.y).length() - minor,
            Sdf::Placed { to_local, inner } => inner.dist(to_local.transform_point3(p)),
            Sdf::Subtract(a, b) => a.dist(p).max(-b.dist(p)),
            Sdf::Intersect(a, b) => a.dist(p).max(b.dist(p)),
        }
    }

    /// A box holding every point where the distance is ≤ 0.
    pub fn bound(&self) -> Aabb {
        let sym = |h: Vec3| Aabb::new(-h, h);
        match self {
            Sdf::Cuboid { half, .. } => sym(*half),
            Sdf::Cylinder { radius, half_height } => sym(Vec3::new(*radius, *half_height, *radius)),
            Sdf::Cone {
                bottom,
                top,
                half_height,
            } => {
                let r = bottom.max(*top);
                sym(Vec3::new(r, *half_height, r))
            }
            Sdf::Sphere { radius } => sym(Vec3::splat(*radius)),
            Sdf::Ellipsoid { radii } => sym(*radii),
            Sdf::Capsule { a, b, radius } => Aabb::new(a.min(*b) - *radius, a.max(*b) + *radius),
            Sdf::Torus { major, minor } => sym(Vec3::new(major + minor, *minor, major + minor)),
            Sdf::Placed { to_local, inner } => inner.bound().transformed(&to_local.inverse()),
            Sdf::Subtract(a, _) => a.bound(),
            Sdf::Intersect(a, b) => {
                let (a, b) = (a.bound(), b.bound());
                Aabb::new(a.min.max(b.min), a.max.min(b.max))
            }
        }
    }
}

/// Exact capped cone (frustum) along y.
fn cone(p: Vec3, r1: f32, r2: f32, h: f32) -> f32 {
    let q = Vec2::new(Vec2::new(p.x, p.z).length(), p.y);
    let k1 = Vec2::new(r2, h);
    let k2 = Vec2::new(r2 - r1, 2.0 * h);
    let ca = Vec2::new(q.x - q.x.min(if q.y < 0.0 { r1 } else { r2 }), q.y.abs() - h);
    let cb = q - k1 + k2 * ((k1 - q).dot(k2) / k2.length_squared()).clamp(0.0, 1.0);
    let s = if cb.x < 0.0 && ca.y < 0.0 { -1.0 } else { 1.0 };
    s * ca.length_squared().min(cb.length_squared()).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distances_of_simple_shapes() {
        let b = Sdf::cuboid(Vec3::new(1.0, 2.0, 3.0), 0.0);
        assert!((b.dist(Vec3::new(2.0, 0.0, 0.0)) - 1.0).abs() < 1e-6);
        assert!((b.dist(Vec3::ZERO) + 1.0).abs() < 1e-6);
        let c = Sdf::cylinder(0.5, 1.0);
        assert!((c.dist(Vec3::new(0.0, 1.5, 0.0)) - 0.5).abs() < 1e-6);
        assert!((c.dist(Vec3::new(1.0, 0.0, 0.0)) - 0.5).abs() < 1e-6);
        // A frustum with equal radii is a cylinder.
        let k = Sdf::cone(0.5, 0.5, 1.0);
        for p in [
            Vec3::new(1.0, 0.2, 0.0),
            Vec3::new(0.1, 1.3, 0.2),
            Vec3::new(0.0, -0.5, 0.3),
        ] {
            assert!((k.dist(p) - c.dist(p)).abs() < 1e-5, "{p}");
        }
        let e = Sdf::ellipsoid(Vec3::splat(0.7));
        assert!((e.dist(Vec3::new(0.0, 1.0, 0.0)) - 0.3).abs() < 1e-5);
        let t = Sdf::torus(1.0, 0.25);
        assert!((t.dist(Vec3::new(1.0, 0.0, 0.0)) + 0.25).abs() < 1e-6);
        let placed = Sdf::sphere(0.5).place(Vec3::new(2.0, 0.0, 0.0), Quat::from_rotation_y(0.7));
        assert!((placed.dist(Vec3::new(2.0, 1.0, 0.0)) - 0.5).abs() < 1e-6);
        assert!(placed.bound().contains(Vec3::new(2.4, 0.0, 0.0)));
        let hollow = Sdf::sphere(1.0).minus(Sdf::sphere(0.5));
        assert!(hollow.dist(Vec3::ZERO) > 0.0 && hollow.dist(Vec3::new(0.75, 0.0, 0.0)) < 0.0);
    }
}
