//! `tabletop`: a plank floor, a plaster back wall, a table (wooden top, blue
//! legs), a terracotta pot with a leafy plant, a white mug with a handle and a
//! small blue box pushed against the mug on the table, and a red ball on the
//! floor. Objects rest on and touch their supports and each other (pot and
//! legs on their supports, box against mug, ball on the floor), and some
//! parts are a few voxels thin (leaves, stems, legs), as in real captures.
//!
//! Colours are chosen so that appearance alone does not separate objects:
//! the table top is floor-coloured wood, the ball is pot-coloured clay red,
//! the box is close to the legs' blue, the mug close to the wall's off-white.

use super::features::Kind;
use super::recipe::{Recipe, View, FLOOR_Y};
use super::sdf::Sdf;
use super::texture::{Material, Rng};
use glam::{Quat, Vec3};
use std::f32::consts::{FRAC_PI_2, PI};

/// Height of the table's top surface.
pub const TABLE_Y: f32 = -0.18;

pub const NAMES: [&str; 7] = ["floor", "wall", "table", "pot", "mug", "ball", "box"];

fn v(x: f32, y: f32, z: f32) -> Vec3 {
    Vec3::new(x, y, z)
}

fn flat(r: f32, g: f32, b: f32) -> Material {
    Material::Flat {
        rgb: v(r, g, b),
        var: 0.04,
    }
}

/// `voxel` is the grid spacing: floor and wall are slabs 2.5 voxels thick so
/// that they stay thin (few occupied voxels) and opaque at any resolution.
pub fn recipe(seed: u64, voxel: f32) -> Recipe {
    let mut r = Recipe::new(View {
        center: v(0.0, -0.32, 0.0),
        radius: 2.6,
        fov_x: 42.0,
        stroke_azimuth: 12.0,
        stroke_elevation: 35.0,
    });
    let slab = 2.5 * voxel;
    let mut rng = Rng::new(seed ^ 0x7AB1E);

    // Floor: boards along x.
    let floor = r.object(
        "floor",
        Kind::Floor,
        &["boards"],
        &[v(-0.75, FLOOR_Y, 0.62), v(-0.1, FLOOR_Y, 0.8), v(0.25, FLOOR_Y, 0.8)],
    );
    r.add(
        floor,
        0,
        Sdf::cuboid(v(0.95, slab / 2.0, 0.95), 0.0).at(v(0.0, FLOOR_Y - slab / 2.0, 0.0)),
        Material::Planks {
            rgb: v(0.66, 0.47, 0.3),
            width: 0.16,
            length: 0.72,
        },
    );

    // Back wall, low enough that orbit views from behind see over it.
    let wall_z = -0.88;
    let wall_top = 0.0;
    let wall = r.object(
        "wall",
        Kind::Wall,
        &["plaster"],
        &[v(-0.75, -0.08, wall_z), v(0.75, -0.08, wall_z)],
    );
    let wall_half = v(0.95, (wall_top - FLOOR_Y + slab) / 2.0, slab / 2.0);
    r.add(
        wall,
        0,
        Sdf::cuboid(wall_half, 0.0).at(v(0.0, FLOOR_Y - slab + wall_half.y, wall_z - slab / 2.0)),
        Material::Flat {
            rgb: v(0.86, 0.84, 0.78),
            var: 0.05,
        },
    );

    // Table: top (base part) and four legs.
    let table = r.object(
        "table",
        Kind::Table,
        &["top", "legs"],
        &[v(-0.5, TABLE_Y, 0.3), v(0.5, TABLE_Y, 0.3)],
    );
    let top_half = v(0.6, 0.02, 0.38);
    r.add(
        table,
        0,
        Sdf::cuboid(top_half, 0.008).at(v(0.0, TABLE_Y - top_half.y, 0.0)),
        Material::Wood {
            rgb: v(0.68, 0.49, 0.31),
        },
    );
    let leg_top = TABLE_Y - 2.0 * top_half.y;
    let leg_half = (leg_top - FLOOR_Y) / 2.0;
    for (x, z) in [(-0.52, -0.3), (0.52, -0.3), (-0.52, 0.3), (0.52, 0.3)] {
        r.add(
            table,
            1,
            Sdf::cylinder(0.032, leg_half).at(v(x, FLOOR_Y + leg_half, z)),
            flat(0.17, 0.21, 0.38),
        );
    }

    // Pot with soil (base part) and a plant of leaf blobs.
    let pot_c = v(-0.24, TABLE_Y, -0.1);
    let pot_h = 0.18;
    let rim_y = pot_c.y + pot_h;
    let soil_y = rim_y - 0.025;
    let pot = r.object(
        "pot",
        Kind::Pot,
        &["pot", "plant"],
        &[pot_c + v(0.0, 0.07, 0.11), pot_c + v(0.02, 0.3, 0.06)],
    );
    let clay = Material::Pot {
        clay: v(0.74, 0.37, 0.22),
        soil: v(0.24, 0.16, 0.1),
        centre: pot_c,
        soil_y,
        soil_radius: 0.096,
    };
    let body = Sdf::cone(0.085, 0.115, pot_h / 2.0)
        .at(pot_c + v(0.0, pot_h / 2.0, 0.0))
        .minus(Sdf::cylinder(0.097, 0.1).at(v(pot_c.x, soil_y + 0.1, pot_c.z)));
    r.add(pot, 0, body, clay.clone());
    r.add(
        pot,
        0,
        Sdf::torus(0.113, 0.016).at(v(pot_c.x, rim_y - 0.01, pot_c.z)),
        clay,
    );
    plant(&mut r, &mut rng, pot, v(pot_c.x, soil_y, pot_c.z));

    // Mug: hollow cylinder (base part) and a handle on its +x side.
    let mug_c = v(0.1, TABLE_Y, 0.1);
    let (mug_r, mug_h) = (0.075, 0.15);
    let mug = r.object(
        "mug",
        Kind::Mug,
        &["body", "handle"],
        &[mug_c + v(-0.03, 0.06, mug_r), mug_c + v(mug_r + 0.05, 0.08, 0.0)],
    );
    let white = Material::Flat {
        rgb: v(0.93, 0.93, 0.91),
        var: 0.02,
    };
    let cup = Sdf::cylinder(mug_r, mug_h / 2.0)
        .at(mug_c + v(0.0, mug_h / 2.0, 0.0))
        .minus(Sdf::cylinder(mug_r - 0.02, mug_h / 2.0).at(mug_c + v(0.0, 0.02 + mug_h / 2.0, 0.0)));
    r.add(mug, 0, cup, white.clone());
    // Coffee inside, so the opening reads as one (renders are unlit).
    let coffee_half = (mug_h - 0.045) / 2.0;
    r.add(
        mug,
        0,
        Sdf::cylinder(mug_r - 0.02, coffee_half).at(mug_c + v(0.0, 0.02 + coffee_half, 0.0)),
        flat(0.3, 0.18, 0.1),
    );
    let handle_c = mug_c + v(mug_r, mug_h * 0.5, 0.0);
    let handle = Sdf::torus(0.048, 0.015)
        .place(handle_c, Quat::from_rotation_x(FRAC_PI_2))
        .and(Sdf::cuboid(v(0.06, 0.08, 0.03), 0.0).at(handle_c + v(0.05, 0.0, 0.0)));
    r.add(mug, 1, handle, white);

    // Ball on the floor, clay red like the pot.
    let ball_c = v(0.5, FLOOR_Y + 0.1, 0.58);
    let ball = r.object(
        "ball",
        Kind::Ball,
        &["ball"],
        &[ball_c + v(-0.06, 0.03, 0.07), ball_c + v(0.05, -0.02, 0.08)],
    );
    r.add(ball, 0, Sdf::sphere(0.1).at(ball_c), flat(0.76, 0.33, 0.21));

    // Small box on the table, blue like the legs, pushed against the mug's
    // body on its -x side (a 4 mm overlap so the two touch at any grid
    // resolution, as real objects in contact do).
    let box_half = v(0.06, 0.05, 0.075);
    let box_c = v(mug_c.x - mug_r - box_half.x + 0.004, TABLE_Y + box_half.y, mug_c.z);
    let bx = r.object(
        "box",
        Kind::Box,
        &["box"],
        &[
            box_c + v(-0.045, 0.05, -0.04),
            box_c + v(-0.015, 0.05, 0.05),
            box_c + v(-0.03, 0.02, 0.075),
        ],
    );
    r.add(bx, 0, Sdf::cuboid(box_half, 0.008).at(box_c), flat(0.2, 0.27, 0.52));
    r
}

/// A few stems and ten leaf blobs (flattened ellipsoids tilted outwards and
/// up), each its own green, rising from the soil at `base`.
fn plant(r: &mut Recipe, rng: &mut Rng, pot: usize, base: Vec3) {
    let stem = flat(0.25, 0.4, 0.15);
    for i in 0..3 {
        let a = i as f32 * 2.1 + rng.range(0.0, 0.5);
        let tip = base + v(0.04 * a.cos(), rng.range(0.16, 0.24), 0.04 * a.sin());
        r.add(pot, 1, Sdf::capsule(base, tip, 0.01), stem.clone());
    }
    let golden = PI * (3.0 - 5f32.sqrt());
    for i in 0..10 {
        let a = i as f32 * golden + rng.range(-0.3, 0.3);
        let up = 0.04 + 0.2 * (i as f32 / 9.0) + rng.range(-0.02, 0.02);
        let out = rng.range(0.06, 0.1) * (1.0 - 0.35 * i as f32 / 9.0);
        let centre = base + v(out * a.cos(), up, out * a.sin());
        // Local x points outwards, tilted up by `pitch`.
        let pitch = rng.range(0.25, 0.7);
        let rot = Quat::from_rotation_y(-a) * Quat::from_rotation_z(pitch);
        let size = rng.range(0.065, 0.085);
        let green = v(rng.range(0.1, 0.3), rng.range(0.38, 0.6), rng.range(0.06, 0.2));
        r.add(
            pot,
            1,
            Sdf::ellipsoid(v(size, 0.018, size * 0.5)).place(centre, rot),
            Material::Flat { rgb: green, var: 0.05 },
        );
    }
}
