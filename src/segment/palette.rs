//! The colours a stroke's pixels show, and whether a voxel shows one.
//!
//! Segmentation asks it twice: which voxels near the stroked surface are
//! what the user stroked ([`super::anchor::seen_by_stroke`], a few thousand
//! voxels, a generous distance), and which voxels of a whole flood (up to
//! a million) look like the stroke (the graph cut's background model, a
//! strict one). The second goes through a [`PaletteTable`] over the RGB
//! cube so that each voxel costs a lookup, not a pass over the palette.

use glam::Vec3;

/// Distinct stroke colours, rounded to 1/64 a channel: an object's
/// strokes show a few hundred at that step, not one per pixel (the
/// rounding, under 0.008 a channel, is nothing against the distances asked).
#[derive(Clone, Debug, Default)]
pub struct Palette {
    colours: Vec<Vec3>,
}

impl Palette {
    pub fn new(pixels: &[Vec3]) -> Self {
        let key = |c: &Vec3| c.to_array().map(|x| (x.clamp(0.0, 1.0) * 64.0).round() as u8);
        let mut keys: Vec<[u8; 3]> = pixels.iter().map(key).collect();
        keys.sort_unstable();
        keys.dedup();
        Palette {
            colours: keys
                .iter()
                .map(|k| Vec3::from_array(k.map(|x| x as f32 / 64.0)))
                .collect(),
        }
    }

    /// Adds `other`'s colours (an object's palette over its strokes).
    pub fn extend(&mut self, other: &Palette) {
        self.colours.extend_from_slice(&other.colours);
        self.colours
            .sort_unstable_by(|a, b| a.to_array().partial_cmp(&b.to_array()).unwrap());
        self.colours.dedup();
    }

    pub fn is_empty(&self) -> bool {
        self.colours.is_empty()
    }

    /// Whether `c` lies within squared RGB distance `reach2` of a colour of
    /// the palette.
    pub fn shows(&self, c: Vec3, reach2: f32) -> bool {
        self.colours.iter().any(|p| (*p - c).length_squared() <= reach2)
    }

    /// [`Self::shows`] at one `reach2`, answered from a table.
    pub fn table(&self, reach2: f32) -> PaletteTable<'_> {
        PaletteTable::new(self, reach2)
    }
}

/// Cells per axis of the RGB cube.
const CELLS: usize = 32;

/// What a cell of the RGB cube holds.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Cell {
    /// No colour of the cell is within reach.
    None,
    /// Some are: ask the palette.
    Some,
    /// Every colour of the cell is within reach.
    All,
}

/// [`Palette::shows`] at one reach, exact: cells of the RGB cube wholly
/// within reach of a palette colour answer yes, cells out of reach of all
/// answer no, and only colours in the cells between ask the palette.
pub struct PaletteTable<'a> {
    palette: &'a Palette,
    reach2: f32,
    cells: Vec<Cell>,
}

impl<'a> PaletteTable<'a> {
    fn new(palette: &'a Palette, reach2: f32) -> Self {
        let mut cells = vec![Cell::None; CELLS * CELLS * CELLS];
        let h = 1.0 / CELLS as f32;
        let span = (reach2.max(0.0).sqrt() / h).ceil() as isize + 1;
        for p in &palette.colours {
            let home = p.to_array().map(|x| cell_of(x) as isize);
            for k in (home[2] - span).max(0)..=(home[2] + span).min(CELLS as isize - 1) {
                for j in (home[1] - span).max(0)..=(home[1] + span).min(CELLS as isize - 1) {
                    for i in (home[0] - span).max(0)..=(home[0] + span).min(CELLS as isize - 1) {
                        let lo = Vec3::new(i as f32, j as f32, k as f32) * h;
                        let hi = lo + Vec3::splat(h);
                        let slot = &mut cells[i as usize + CELLS * (j as usize + CELLS * k as usize)];
                        // Farthest corner within reach: the whole cell is.
                        let far = (*p - lo).abs().max((*p - hi).abs());
                        if far.length_squared() <= reach2 {
                            *slot = Cell::All;
                        } else if *slot == Cell::None && (p.clamp(lo, hi) - *p).length_squared() <= reach2 {
                            *slot = Cell::Some;
                        }
                    }
                }
            }
        }
        PaletteTable { palette, reach2, cells }
    }

    pub fn shows(&self, c: Vec3) -> bool {
        // The cells cover the cube; a colour outside it asks the palette.
        if c.min_element() < 0.0 || c.max_element() > 1.0 {
            return self.palette.shows(c, self.reach2);
        }
        let [i, j, k] = c.to_array().map(cell_of);
        match self.cells[i + CELLS * (j + CELLS * k)] {
            Cell::None => false,
            Cell::All => true,
            Cell::Some => self.palette.shows(c, self.reach2),
        }
    }
}

/// The cell of a channel value in [0, 1] (1 goes to the last cell).
fn cell_of(x: f32) -> usize {
    ((x * CELLS as f32).floor().max(0.0) as usize).min(CELLS - 1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::SplitMix64;

    /// The table answers as the palette does, colour for colour, at a
    /// strict and a generous reach (random palettes and colours, some just
    /// outside the cube).
    #[test]
    fn the_table_answers_as_the_palette() {
        let mut rng = SplitMix64::new(7);
        let mut colour =
            || Vec3::new(rng.unit() as f32, rng.unit() as f32, rng.unit() as f32) * 1.1 - Vec3::splat(0.05);
        for (n, reach2) in [(1, 0.02), (40, 0.02), (300, 0.02), (25, 0.3)] {
            let pixels: Vec<Vec3> = (0..n).map(|_| colour()).collect();
            let palette = Palette::new(&pixels);
            let table = palette.table(reach2);
            let (mut yes, mut no) = (0, 0);
            for _ in 0..20_000 {
                let c = colour();
                let want = palette.shows(c, reach2);
                assert_eq!(table.shows(c), want, "{c} at reach² {reach2}");
                if want {
                    yes += 1
                } else {
                    no += 1
                }
            }
            assert!(yes > 0 && no > 0, "both answers tested: {yes} yes, {no} no");
        }
    }

    /// Known answers: pixels are rounded to 1/64 and repeats dropped.
    #[test]
    fn the_palette_keeps_each_rounded_colour_once() {
        let red = Vec3::new(0.9, 0.1, 0.1);
        let palette = Palette::new(&[red, red + Vec3::splat(0.0005), Vec3::new(0.1, 0.1, 0.9)]);
        assert_eq!(palette.colours.len(), 2);
        // An object's palette over two strokes keeps each colour once.
        let mut object = palette.clone();
        object.extend(&palette);
        object.extend(&Palette::new(&[Vec3::ZERO]));
        assert_eq!(object.colours.len(), 3);
        assert!(palette.shows(Vec3::new(0.8, 0.15, 0.1), 0.02));
        assert!(!palette.shows(Vec3::new(0.5, 0.5, 0.5), 0.02));
        assert!(Palette::new(&[]).is_empty());
    }
}
