//! A scene recipe: objects made of parts, parts made of SDF primitives with a
//! material, and how to look at the result. Scene modules (`tabletop`,
//! `shelf`) write recipes; `voxelize` turns them into fields.

use super::features::Kind;
use super::sdf::Sdf;
use super::texture::Material;
use glam::Vec3;

/// Height of the floor's top surface in every demo scene (y is up), so that
/// scenes compose by moving in x and z only.
pub const FLOOR_Y: f32 = -0.6;

/// Most parts one object may have (per-voxel part weights live on the stack).
pub const MAX_PARTS: usize = 8;

/// One primitive of one part of one object.
#[derive(Clone, Debug)]
pub struct Prim {
    /// Index into `Recipe::objects` (label − 1).
    pub object: usize,
    /// Index into the object's `parts` (0 = base part).
    pub part: usize,
    pub sdf: Sdf,
    pub material: Material,
}

#[derive(Clone, Debug)]
pub struct ObjectSpec {
    pub name: &'static str,
    pub kind: Kind,
    pub parts: Vec<&'static str>,
    /// World points (on or inside the object) that the built-in stroke
    /// passes near, in order; the stroke follows their projections on the
    /// stroke camera and keeps the surface points that belong to the object.
    pub anchors: Vec<Vec3>,
}

/// Where the cameras go: an orbit around `center` and a stroke view.
#[derive(Clone, Copy, Debug)]
pub struct View {
    pub center: Vec3,
    pub radius: f32,
    /// Horizontal field of view, degrees.
    pub fov_x: f32,
    /// Stroke camera azimuth (degrees from +z towards +x) and elevation.
    pub stroke_azimuth: f32,
    pub stroke_elevation: f32,
}

#[derive(Clone, Debug)]
pub struct Recipe {
    pub objects: Vec<ObjectSpec>,
    pub prims: Vec<Prim>,
    pub view: View,
}

impl Recipe {
    pub fn new(view: View) -> Self {
        Recipe {
            objects: vec![],
            prims: vec![],
            view,
        }
    }
    /// Adds an object; returns its index.
    pub fn object(&mut self, name: &'static str, kind: Kind, parts: &[&'static str], anchors: &[Vec3]) -> usize {
        self.objects.push(ObjectSpec {
            name,
            kind,
            parts: parts.to_vec(),
            anchors: anchors.to_vec(),
        });
        self.objects.len() - 1
    }
    pub fn add(&mut self, object: usize, part: usize, sdf: Sdf, material: Material) {
        self.prims.push(Prim {
            object,
            part,
            sdf,
            material,
        });
    }
}
