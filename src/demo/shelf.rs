//! `shelf`: a free-standing wooden shelf (boards + sides) holding a toy
//! excavator (yellow body and arm, grey bucket, black tracks), a row of books
//! and a honey jar. No floor or wall, so it composes into `tabletop`; its
//! bottom stands at the shared floor height, so a move in x/z places it.
//!
//! Appearance confusions again: the jar's amber is close to the excavator's
//! yellow, the ochre book close to both, the shelf wood close to the table's.

use super::features::Kind;
use super::recipe::{Recipe, View, FLOOR_Y};
use super::sdf::Sdf;
use super::texture::{Material, Rng};
use glam::{Quat, Vec3};

pub const NAMES: [&str; 4] = ["shelf", "excavator", "books", "jar"];

fn v(x: f32, y: f32, z: f32) -> Vec3 {
    Vec3::new(x, y, z)
}

fn flat(rgb: Vec3) -> Material {
    Material::Flat { rgb, var: 0.04 }
}

pub fn recipe(seed: u64, _voxel: f32) -> Recipe {
    let mut r = Recipe::new(View {
        center: v(0.0, -0.15, 0.0),
        radius: 2.7,
        fov_x: 40.0,
        stroke_azimuth: -12.0,
        stroke_elevation: 18.0,
    });
    let mut rng = Rng::new(seed ^ 0x5E1F);
    let (half_w, depth, top) = (0.6, 0.18, 0.35);
    let board = 0.035;
    // Top surfaces of the bottom and middle boards.
    let low = -0.505;
    let mid = -0.085;

    let shelf = r.object(
        "shelf",
        Kind::Shelf,
        &["boards", "sides"],
        // Along the top board and down the right side's inner face (the
        // face the stroke camera, left of centre, sees; the side's front
        // edge is narrower than the brush, and a stroke ending there
        // stopped on the top board: the sides were never stroked).
        &[v(-0.45, top, 0.14), v(0.52, top, 0.14), v(half_w - board, 0.0, 0.09)],
    );
    let wood = Material::Wood {
        rgb: v(0.74, 0.56, 0.37),
    };
    let inner = half_w - board;
    for y in [low, mid, top] {
        r.add(
            shelf,
            0,
            Sdf::cuboid(v(inner, board / 2.0, depth), 0.004).at(v(0.0, y - board / 2.0, 0.0)),
            wood.clone(),
        );
    }
    let side_half = v(board / 2.0, (top - FLOOR_Y) / 2.0, depth);
    for s in [-1.0, 1.0] {
        r.add(
            shelf,
            1,
            Sdf::cuboid(side_half, 0.004).at(v(s * (half_w - board / 2.0), FLOOR_Y + side_half.y, 0.0)),
            Material::Wood {
                rgb: v(0.6, 0.43, 0.27),
            },
        );
    }

    excavator(&mut r, v(-0.24, mid, 0.0));

    // Books standing on the bottom board, touching each other.
    let books = r.object(
        "books",
        Kind::Books,
        &["book", "book 2", "book 3", "book 4"],
        &[v(0.06, low + 0.13, 0.2), v(0.28, low + 0.12, 0.2)],
    );
    let colours = [
        v(0.55, 0.12, 0.12),
        v(0.12, 0.16, 0.4),
        v(0.15, 0.38, 0.2),
        v(0.8, 0.6, 0.2),
    ];
    let mut x = 0.05;
    for (i, rgb) in colours.into_iter().enumerate() {
        let w = rng.range(0.04, 0.06);
        let h = rng.range(0.22, 0.3);
        let d = rng.range(0.15, 0.17);
        r.add(
            books,
            i,
            Sdf::cuboid(v(w / 2.0, h / 2.0, d), 0.004).at(v(x + w / 2.0, low + h / 2.0, 0.0)),
            flat(rgb),
        );
        x += w;
    }

    // Honey jar with a red lid on the middle board, against the
    // excavator's bucket (amber next to yellow: a similar-looking neighbour).
    let jar_c = v(0.185, mid, 0.0);
    let jar = r.object(
        "jar",
        Kind::Jar,
        &["jar", "lid"],
        &[jar_c + v(0.0, 0.06, 0.07), jar_c + v(0.01, 0.165, 0.05)],
    );
    r.add(
        jar,
        0,
        Sdf::cylinder(0.07, 0.075).at(jar_c + v(0.0, 0.075, 0.0)),
        Material::Flat {
            rgb: v(0.86, 0.6, 0.13),
            var: 0.06,
        },
    );
    r.add(
        jar,
        1,
        Sdf::cylinder(0.074, 0.016).at(jar_c + v(0.0, 0.166, 0.0)),
        flat(v(0.7, 0.16, 0.12)),
    );
    r
}

/// A toy excavator standing at `at` (bottom centre of its tracks): body and
/// cab (base part), boom and stick (arm), bucket, and two tracks.
fn excavator(r: &mut Recipe, at: Vec3) {
    let ex = r.object(
        "excavator",
        Kind::Excavator,
        &["body", "arm", "bucket", "tracks"],
        &[
            at + v(-0.06, 0.1, 0.09),
            at + v(0.02, 0.14, 0.07),
            at + v(0.15, 0.23, -0.02),
        ],
    );
    let yellow = v(0.95, 0.74, 0.1);
    let track_half = v(0.13, 0.032, 0.028);
    for s in [-1.0, 1.0] {
        r.add(
            ex,
            3,
            Sdf::cuboid(track_half, 0.022).at(at + v(0.0, track_half.y, s * 0.058)),
            Material::Treads {
                rgb: v(0.08, 0.08, 0.08),
                period: 0.03,
            },
        );
    }
    let body_y = 2.0 * track_half.y;
    r.add(
        ex,
        0,
        Sdf::cuboid(v(0.1, 0.035, 0.085), 0.01).at(at + v(0.0, body_y + 0.035, 0.0)),
        flat(yellow),
    );
    let cab_c = at + v(0.02, body_y + 0.07 + 0.05, 0.035);
    r.add(
        ex,
        0,
        Sdf::cuboid(v(0.045, 0.05, 0.045), 0.008).at(cab_c),
        Material::Cab {
            rgb: yellow,
            window: v(0.15, 0.2, 0.25),
            y0: cab_c.y + 0.0,
            y1: cab_c.y + 0.035,
        },
    );
    r.add(
        ex,
        0,
        Sdf::cuboid(v(0.025, 0.028, 0.075), 0.008).at(at + v(-0.075, body_y + 0.07 + 0.028, -0.005)),
        flat(yellow * 0.85),
    );
    let arm = flat(v(0.92, 0.68, 0.08));
    let (shoulder, elbow, wrist) = (
        at + v(0.05, body_y + 0.055, -0.035),
        at + v(0.2, body_y + 0.2, -0.035),
        at + v(0.29, body_y + 0.03, -0.035),
    );
    r.add(ex, 1, Sdf::capsule(shoulder, elbow, 0.02), arm.clone());
    r.add(ex, 1, Sdf::capsule(elbow, wrist, 0.016), arm);
    r.add(
        ex,
        2,
        Sdf::cuboid(v(0.035, 0.03, 0.045), 0.008).place(wrist + v(0.015, -0.02, 0.0), Quat::from_rotation_z(0.5)),
        flat(v(0.32, 0.32, 0.3)),
    );
}
