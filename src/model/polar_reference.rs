//! Each frame's own polar cut: the direction about the hub in which a frame differs most from
//! the still background moves the keypoints' angle cut to the opposite side of the arm.
//!
//! With one fixed cut, a link that sweeps past it (a reacher's tip sweeps more than a turn)
//! makes every keypoint that sees it jump by `2 pi` there, and the chart folds. Measured
//! from the frame's own direction `psi`, each cell's angle is `Psi + wrap(theta - psi)`:
//! the arm's cells never reach the cut opposite `psi`, and `Psi`, the angle of `psi` itself,
//! is cut where the dataset's directions never point. A cell of still background opposite the
//! arm would jump by `2 pi` as the cut sweeps over it, so its angle from `psi` fades to 0
//! over the last [`CUT_FADE`] before the cut: each cell's value is continuous in `psi`.

use super::{POLAR_FADE_RADIUS, pixel_input};
use crate::envs::{FRAME_BYTES, FRAME_PX};

/// The angle from `psi` over which a cell's offset fades to 0 before the cut opposite `psi`.
/// An arm's cells lie within about 120 degrees of its direction (a tip folded back by 167
/// degrees, the direction pulled 30 degrees towards it), short of the fade.
const CUT_FADE: f32 = std::f32::consts::FRAC_PI_4;

/// Bins of the dataset's directions when placing their cut: 2.5 degrees each.
const DIRECTION_BINS: usize = 144;

/// A frame's direction about the hub and the per-cell angles it gives.
#[derive(Debug, Clone)]
pub(crate) struct PolarReference {
    /// The still background, each pixel's channels as the network sees them.
    background: Vec<f32>,
    /// Per pixel: `(cos, sin)` of its angle about the centre, faded to 0 at the centre.
    pixel_direction: Vec<[f32; 2]>,
    /// Angle `m` of the directions' own axis: `Psi` runs over `(m - pi, m + pi]`.
    axis: f32,
    /// Per keypoint cell: its angle about the centre, its fade towards the centre (where the
    /// angle is undefined) and the falloff weight of its angle.
    cells: Vec<CellPolar>,
}

#[derive(Debug, Clone, Copy)]
struct CellPolar {
    angle: f32,
    fade: f32,
    weight: f32,
}

fn wrap(angle: f32) -> f32 {
    use std::f32::consts::{PI, TAU};
    let a = angle.rem_euclid(TAU);
    if a > PI { a - TAU } else { a }
}

impl PolarReference {
    /// The reference about `centre` (image coordinates) for maps of `side x side` cells, from
    /// `background` (`FRAME_BYTES` network inputs) and the directions' axis `(cos m, sin m)`;
    /// `falloff` as [`super::EncoderConfig::polar_angle_falloff`] (0: off).
    pub(crate) fn new(
        centre: [f32; 2],
        background: Vec<f32>,
        [cos_m, sin_m]: [f32; 2],
        side: usize,
        falloff: f64,
    ) -> Self {
        let polar = |x: f32, y: f32| {
            let (dx, dy) = (x - centre[0], y - centre[1]);
            let r2 = dx * dx + dy * dy;
            let fade = r2 / (r2 + POLAR_FADE_RADIUS * POLAR_FADE_RADIUS);
            (dy.atan2(dx), r2.sqrt(), fade)
        };
        let coord = |i: usize, n: usize| (2.0 * i as f32 + 1.0) / n as f32 - 1.0;
        let pixel_direction = (0..FRAME_PX * FRAME_PX)
            .map(|p| {
                let (angle, _, fade) =
                    polar(coord(p % FRAME_PX, FRAME_PX), coord(p / FRAME_PX, FRAME_PX));
                [fade * angle.cos(), fade * angle.sin()]
            })
            .collect();
        let cells = (0..side * side)
            .map(|c| {
                let (angle, radius, fade) = polar(coord(c % side, side), coord(c / side, side));
                let weight = if falloff > 0.0 {
                    1.0 / (1.0 + (radius / falloff as f32).powi(2))
                } else {
                    1.0
                };
                CellPolar {
                    angle,
                    fade,
                    weight,
                }
            })
            .collect();
        Self {
            background,
            pixel_direction,
            axis: sin_m.atan2(cos_m),
            cells,
        }
    }

    /// The still background of `frames`: each pixel channel's median, as network inputs.
    pub(crate) fn background_of<'a>(frames: impl Iterator<Item = &'a [u8]>) -> Vec<f32> {
        let mut counts = vec![[0u32; 256]; FRAME_BYTES];
        let mut n = 0u32;
        for frame in frames {
            for (count, &b) in counts.iter_mut().zip(frame) {
                count[b as usize] += 1;
            }
            n += 1;
        }
        counts
            .iter()
            .map(|count| {
                let mut seen = 0;
                let median = count
                    .iter()
                    .position(|&c| {
                        seen += c;
                        2 * seen > n
                    })
                    .unwrap_or(0);
                pixel_input(median as u8)
            })
            .collect()
    }

    /// `psi`: the angle about the centre of the frame's difference from the background
    /// (`input`: the frame's `FRAME_BYTES` network inputs, channels innermost).
    pub(crate) fn direction(&self, input: &[f32]) -> f32 {
        let (mut c, mut s) = (0.0f64, 0.0f64);
        let pixels = input.chunks_exact(3).zip(self.background.chunks_exact(3));
        for ((x, b), [dc, ds]) in pixels.zip(&self.pixel_direction) {
            let d: f32 = x.iter().zip(b).map(|(x, b)| (x - b).abs()).sum();
            c += f64::from(d * dc);
            s += f64::from(d * ds);
        }
        (s.atan2(c)) as f32
    }

    /// The cells' angles for a frame of direction `psi` (see the module's doc), each weighed
    /// by its falloff, into `out` (`[cells]`).
    pub(crate) fn angle_grid(&self, psi: f32, out: &mut [f32]) {
        use std::f32::consts::PI;
        let big_psi = wrap(psi - self.axis);
        for (o, cell) in out.iter_mut().zip(&self.cells) {
            let offset = wrap(cell.angle - psi);
            let before_cut = ((PI - offset.abs()) / CUT_FADE).min(1.0);
            *o = (big_psi + cell.fade * offset * before_cut) * cell.weight;
        }
    }

    /// Cells in each angle grid.
    pub(crate) fn cells(&self) -> usize {
        self.cells.len()
    }

    /// The axis `(cos m, sin m)` for `directions` (radians): opposite the middle of the
    /// widest sector none of them points into (the least visited one if every sector is).
    pub(crate) fn axis_for(directions: impl Iterator<Item = f32>) -> [f32; 2] {
        use std::f32::consts::{PI, TAU};
        let mut counts = [0u32; DIRECTION_BINS];
        for d in directions {
            let bin = ((d + PI) / TAU * DIRECTION_BINS as f32) as usize;
            counts[bin.min(DIRECTION_BINS - 1)] += 1;
        }
        let least = counts.iter().copied().min().unwrap_or(0);
        // The longest circular run of the least-visited bins.
        let (mut best, mut best_end, mut run) = (0, 0, 0);
        for i in 0..2 * DIRECTION_BINS {
            if counts[i % DIRECTION_BINS] == least {
                run += 1;
                if run > best && run <= DIRECTION_BINS {
                    (best, best_end) = (run, i);
                }
            } else {
                run = 0;
            }
        }
        let middle = best_end as f32 + 0.5 - best as f32 / 2.0;
        let cut = middle / DIRECTION_BINS as f32 * TAU - PI;
        let m = cut + PI;
        [m.cos(), m.sin()]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrap_keeps_angles_in_a_half_open_turn() {
        use std::f32::consts::PI;
        assert!((wrap(3.0 * PI / 2.0) + PI / 2.0).abs() < 1e-6);
        assert!((wrap(-3.0 * PI / 2.0) - PI / 2.0).abs() < 1e-6);
        assert!((wrap(0.25) - 0.25).abs() < 1e-7);
    }

    #[test]
    fn a_cells_value_is_continuous_as_the_cut_sweeps_over_it() {
        let reference =
            PolarReference::new([0.0, 0.0], vec![0.0; FRAME_BYTES], [1.0, 0.0], 32, 0.4);
        let mut before = vec![0.0; reference.cells()];
        let mut after = before.clone();
        // The cell at the corner, 225 degrees (-135); the cut opposite psi crosses it at
        // psi = 45 degrees.
        let cell = 0;
        let angle = reference.cells[cell].angle;
        assert!((angle.to_degrees() + 135.0).abs() < 1e-3);
        let eps = 1e-3;
        reference.angle_grid(angle + std::f32::consts::PI - eps, &mut before);
        reference.angle_grid(angle + std::f32::consts::PI + eps, &mut after);
        assert!(
            (before[cell] - after[cell]).abs() < 1e-2,
            "{} {}",
            before[cell],
            after[cell]
        );
    }

    #[test]
    fn the_axis_lies_opposite_the_widest_empty_sector() {
        // Directions everywhere but 150..200 degrees: the cut at 175, the axis at -5.
        let directions = (0..3600)
            .map(|i| (i as f32 / 10.0 - 180.0).to_radians())
            .filter(|d| !(150.0..200.0).contains(&d.to_degrees().rem_euclid(360.0)));
        let [c, s] = PolarReference::axis_for(directions);
        let m = s.atan2(c).to_degrees();
        assert!((m + 5.0).abs() < 2.0, "{m}");
    }

    #[test]
    fn a_bar_about_the_centre_points_the_direction_and_no_cell_of_it_reaches_the_cut() {
        // A dark bar from the centre towards 170 degrees on a light background.
        let background = vec![0.5f32; FRAME_BYTES];
        let mut frame = background.clone();
        let coord = |i: usize| (2.0 * i as f32 + 1.0) / FRAME_PX as f32 - 1.0;
        let along = 170f32.to_radians();
        for p in 0..FRAME_PX * FRAME_PX {
            let (x, y) = (coord(p % FRAME_PX), coord(p / FRAME_PX));
            let t = x * along.cos() + y * along.sin();
            let off = (y * along.cos() - x * along.sin()).abs();
            if t > 0.0 && t < 0.8 && off < 0.06 {
                frame[3 * p..3 * p + 3].fill(-0.5);
            }
        }
        // The directions' own cut at 180 degrees, the axis at 0: the bar is near that cut.
        let reference = PolarReference::new([0.0, 0.0], background, [1.0, 0.0], 32, 0.0);
        let psi = reference.direction(&frame);
        assert!(
            (psi.to_degrees() - 170.0).abs() < 1.0,
            "{}",
            psi.to_degrees()
        );
        let mut grid = vec![0.0; reference.cells()];
        reference.angle_grid(psi, &mut grid);
        // Cells on the bar past 180 degrees read beyond pi, not from -pi: no jump along it.
        let coord32 = |i: usize| (2.0 * i as f32 + 1.0) / 32.0 - 1.0;
        for (c, &v) in grid.iter().enumerate() {
            let (x, y) = (coord32(c % 32), coord32(c / 32));
            if (x * x + y * y).sqrt() > 0.2 {
                let theta = y.atan2(x);
                let unwrapped = if theta < 0.0 {
                    theta + std::f32::consts::TAU
                } else {
                    theta
                };
                if (unwrapped.to_degrees() - 170.0).abs() < 30.0 {
                    let r2 = x * x + y * y;
                    let fade = r2 / (r2 + POLAR_FADE_RADIUS * POLAR_FADE_RADIUS);
                    let want = psi + fade * (unwrapped - psi);
                    assert!((v - want).abs() < 1e-5, "cell {c}: {v} vs {want}");
                }
            }
        }
    }
}
