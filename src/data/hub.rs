//! Where a dataset's frames turn: each pixel's spread over the frames, the hub a revolute
//! system turns about (if it has one), and the direction about a centre in which the frames
//! change least.
//!
//! Image coordinates here are the encoder's: `x` along the columns and `y` down the rows, both
//! in `[-1, 1]` across the frame, `(0, 0)` at its centre.

use crate::envs::{FRAME_BYTES, FRAME_PX};

/// Smallest share of the spread's variance the radial profile about a hub must explain. An
/// arm's spread is a function of the distance from its base (0.95-0.98 for procl's reacher, with
/// the base at the centre or moved off it); a moving ball's or a gripper's is not (0.20 and 0.68
/// for the point mass and Fetch).
pub const HUB_MIN_RADIAL_R2: f64 = 0.8;
/// Largest mean spread within [`HUB_CORE_RADIUS_PX`] of a hub, as a share of the radial
/// profile's peak. An arm's base is covered in every frame, so it does not change (0.04-0.07
/// for the reacher and two variants); where a ball or a gripper passes, nothing is always
/// covered (0.89 and 0.99 for the point mass and Fetch).
pub const HUB_MAX_CORE_SHARE: f64 = 0.25;
/// Radius, pixels, of the core whose spread [`HUB_MAX_CORE_SHARE`] bounds.
pub const HUB_CORE_RADIUS_PX: f64 = 1.5;
/// Candidate hubs lie at least this many pixels inside the frame: nearer its edge, the radial
/// profile sees too little of the circle about them to tell a hub.
const HUB_MARGIN_PX: usize = 8;
/// Pixels nearer the centre than this (image units) are weighed by
/// [`PixelSpread::quietest_direction`] as if this far: a weight of `1 / r` would blow up there,
/// where the angle means nothing.
const MIN_WEIGHT_RADIUS: f64 = 0.05;

/// Each pixel's standard deviation over a set of frames, summed over the three channels:
/// zero where nothing ever changes.
#[derive(Debug, Clone)]
pub struct PixelSpread {
    /// `FRAME_PX * FRAME_PX`, row-major.
    std: Vec<f64>,
}

/// A hub found in a [`PixelSpread`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hub {
    /// Image coordinates of the hub.
    pub centre: [f64; 2],
    /// Share of the spread's variance explained by its radial profile about `centre`.
    pub radial_r2: f64,
    /// Mean spread within [`HUB_CORE_RADIUS_PX`] of `centre` over the profile's peak.
    pub core_share: f64,
}

impl Hub {
    /// Whether this candidate is a hub: [`HUB_MIN_RADIAL_R2`] and [`HUB_MAX_CORE_SHARE`] hold.
    pub fn is_accepted(&self) -> bool {
        self.radial_r2 >= HUB_MIN_RADIAL_R2 && self.core_share <= HUB_MAX_CORE_SHARE
    }

    /// The hub in pixels from the frame's top-left corner (`(32, 32)` is its centre).
    pub fn pixels(&self) -> [f64; 2] {
        self.centre.map(|c| (c + 1.0) * FRAME_PX as f64 / 2.0)
    }
}

impl PixelSpread {
    /// The spread of `frames` (RGB u8, 64x64).
    pub fn of_frames<'a>(frames: impl Iterator<Item = &'a [u8]>) -> Self {
        let mut sum = vec![0f64; FRAME_BYTES];
        let mut sum_squares = vec![0f64; FRAME_BYTES];
        let mut count = 0usize;
        for frame in frames {
            for ((s, q), &byte) in sum.iter_mut().zip(&mut sum_squares).zip(frame) {
                let x = byte as f64;
                *s += x;
                *q += x * x;
            }
            count += 1;
        }
        let n = count.max(1) as f64;
        let std = sum
            .chunks_exact(3)
            .zip(sum_squares.chunks_exact(3))
            .map(|(s, q)| {
                (0..3)
                    .map(|c| (q[c] / n - (s[c] / n).powi(2)).max(0.0).sqrt())
                    .sum()
            })
            .collect();
        Self { std }
    }

    /// The point the frames turn about, if they turn about one: the [`Self::hub_candidate`]
    /// when its profile explains at least [`HUB_MIN_RADIAL_R2`] of the variance and the core
    /// about it is quiet ([`HUB_MAX_CORE_SHARE`]): the base of an arm is covered in every frame.
    pub fn hub(&self) -> Option<Hub> {
        self.hub_candidate().filter(Hub::is_accepted)
    }

    /// The centre about which the spread is best explained by a function of the distance alone
    /// (a piecewise-linear radial profile with 1-pixel knots, fitted by least squares; searched
    /// on a 1-pixel grid, then on a quarter-pixel grid about the best), whether or not it is a
    /// hub; `None` for frames that never change.
    pub fn hub_candidate(&self) -> Option<Hub> {
        let total = self.total_variance();
        if total <= 0.0 {
            return None;
        }
        let span = HUB_MARGIN_PX..=FRAME_PX - HUB_MARGIN_PX;
        let coarse = span
            .clone()
            .flat_map(|row| span.clone().map(move |col| [col as f64, row as f64]))
            .map(|c| (self.radial_fit(c, total).0, c))
            .max_by(|a, b| a.0.total_cmp(&b.0))?;
        let [col, row] = coarse.1;
        let fine = (-4..=4)
            .flat_map(|i| (-4..=4).map(move |j| [col + 0.25 * j as f64, row + 0.25 * i as f64]))
            .map(|c| (self.radial_fit(c, total), c))
            .max_by(|a, b| a.0.0.total_cmp(&b.0.0))?;
        let ((radial_r2, profile_peak), pixels) = fine;
        Some(Hub {
            centre: image_point(pixels),
            radial_r2,
            core_share: self.core_mean(pixels) / profile_peak.max(f64::MIN_POSITIVE),
        })
    }

    /// The unit direction (image coordinates) about `centre` in which the frames change
    /// least: each pixel's spread, divided by its distance from `centre` and binned by its
    /// angle about it in 5-degree bins, smoothed over +-15 degrees; the emptiest bin. For an
    /// arm with joint limits about its hub, that is the sector its links never sweep.
    pub fn quietest_direction(&self, centre: [f64; 2]) -> [f64; 2] {
        const BINS: usize = 72;
        const SMOOTH: isize = 3;
        // Each pixel is spread over SUB x SUB points across its area: a pixel next to the
        // centre spans tens of degrees, and binned by its midpoint alone it would drop its
        // heavy `1 / r` weight into one bin, which a shift of the centre by a hundredth of a
        // pixel moves to the next (the cut then jumps between the ends of the quiet sector).
        const SUB: usize = 4;
        let pixel = 2.0 / FRAME_PX as f64;
        let offsets: [f64; SUB] =
            std::array::from_fn(|i| ((i as f64 + 0.5) / SUB as f64 - 0.5) * pixel);
        let mut histogram = [0f64; BINS];
        for (p, &w) in self.std.iter().enumerate() {
            let [px, py] = pixel_coordinates(p);
            for dy in &offsets {
                for dx in &offsets {
                    let (x, y) = (px + dx - centre[0], py + dy - centre[1]);
                    let turn = y.atan2(x).rem_euclid(std::f64::consts::TAU) / std::f64::consts::TAU;
                    // 1 / r: every distance from the centre counts equally per angle (there
                    // are r times more pixels per degree at radius r), so an arm's inner link,
                    // whose sweep is bounded by the joint limit, weighs as much as the outer
                    // one, whose sweep overhangs it.
                    let r = x.hypot(y).max(MIN_WEIGHT_RADIUS);
                    histogram[((turn * BINS as f64) as usize).min(BINS - 1)] += w / r;
                }
            }
        }
        let smoothed = |b: usize| -> f64 {
            (-SMOOTH..=SMOOTH)
                .map(|d| histogram[(b as isize + d).rem_euclid(BINS as isize) as usize])
                .sum()
        };
        let quietest = (0..BINS)
            .min_by(|&a, &b| smoothed(a).total_cmp(&smoothed(b)))
            .unwrap_or(0);
        let angle = (quietest as f64 + 0.5) / BINS as f64 * std::f64::consts::TAU;
        [angle.cos(), angle.sin()]
    }

    /// [`Self::quietest_direction`] about `centre` as an angle in degrees, `[0, 360)`: 0
    /// along the columns, 90 down the rows. A polar head about `centre` is cut there.
    pub fn quietest_angle_deg(&self, centre: [f64; 2]) -> f64 {
        let [x, y] = self.quietest_direction(centre);
        y.atan2(x).to_degrees().rem_euclid(360.0)
    }

    fn total_variance(&self) -> f64 {
        let mean = self.std.iter().sum::<f64>() / self.std.len() as f64;
        self.std.iter().map(|s| (s - mean).powi(2)).sum()
    }

    /// Least-squares fit of the spread by a piecewise-linear function of the distance (knots
    /// every pixel) from `centre` (pixels): the share of `total` variance it explains and the
    /// profile's largest knot value.
    fn radial_fit(&self, centre: [f64; 2], total: f64) -> (f64, f64) {
        let knots = (2.0 * FRAME_PX as f64).ceil() as usize + 2;
        // Normal equations of the hat-function basis: a tridiagonal system.
        let mut diagonal = vec![0f64; knots];
        let mut upper = vec![0f64; knots];
        let mut rhs = vec![0f64; knots];
        let placed: Vec<(usize, f64, f64)> = self
            .std
            .iter()
            .enumerate()
            .map(|(p, &s)| {
                let r = pixel_distance(p, centre);
                let knot = r.floor() as usize;
                (knot, r - knot as f64, s)
            })
            .collect();
        for &(k, w, s) in &placed {
            diagonal[k] += (1.0 - w) * (1.0 - w);
            diagonal[k + 1] += w * w;
            upper[k] += (1.0 - w) * w;
            rhs[k] += (1.0 - w) * s;
            rhs[k + 1] += w * s;
        }
        // Knots no pixel reaches get a tiny ridge and stay at 0.
        for d in &mut diagonal {
            *d += 1e-9;
        }
        let profile = solve_tridiagonal(&diagonal, &upper, &rhs);
        let residual: f64 = placed
            .iter()
            .map(|&(k, w, s)| (s - (1.0 - w) * profile[k] - w * profile[k + 1]).powi(2))
            .sum();
        let peak = profile.iter().copied().fold(0.0, f64::max);
        (1.0 - residual / total, peak)
    }

    fn core_mean(&self, centre: [f64; 2]) -> f64 {
        let (sum, count) = self
            .std
            .iter()
            .enumerate()
            .filter(|&(p, _)| pixel_distance(p, centre) <= HUB_CORE_RADIUS_PX)
            .fold((0.0, 0usize), |(sum, count), (_, &s)| (sum + s, count + 1));
        sum / count.max(1) as f64
    }
}

/// Image coordinates of a point given in pixels from the frame's top-left corner (the inverse
/// of [`Hub::pixels`]).
fn image_point(pixels: [f64; 2]) -> [f64; 2] {
    pixels.map(|p| 2.0 * p / FRAME_PX as f64 - 1.0)
}

/// Image coordinates of pixel `p`'s centre (row-major index).
fn pixel_coordinates(p: usize) -> [f64; 2] {
    image_point([(p % FRAME_PX) as f64 + 0.5, (p / FRAME_PX) as f64 + 0.5])
}

/// Distance in pixels from pixel `p`'s centre to `centre` (pixels from the top-left corner).
fn pixel_distance(p: usize, centre: [f64; 2]) -> f64 {
    let (col, row) = ((p % FRAME_PX) as f64 + 0.5, (p / FRAME_PX) as f64 + 0.5);
    (col - centre[0]).hypot(row - centre[1])
}

/// Solves the symmetric tridiagonal system with `diagonal` and `upper` (`upper[i]` couples
/// `i` and `i + 1`) for `rhs` (Thomas algorithm; the normal equations are positive definite).
fn solve_tridiagonal(diagonal: &[f64], upper: &[f64], rhs: &[f64]) -> Vec<f64> {
    let n = diagonal.len();
    let mut c = vec![0f64; n];
    let mut d = vec![0f64; n];
    for i in 0..n {
        let below = if i == 0 { 0.0 } else { upper[i - 1] };
        let pivot = diagonal[i] - below * if i == 0 { 0.0 } else { c[i - 1] };
        c[i] = upper[i] / pivot;
        d[i] = (rhs[i] - below * if i == 0 { 0.0 } else { d[i - 1] }) / pivot;
    }
    let mut x = d;
    for i in (0..n.saturating_sub(1)).rev() {
        x[i] -= c[i] * x[i + 1];
    }
    x
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::envs::{EnvConfig, EnvKind, ReacherConfig};

    fn spread_of(config: &EnvConfig, frames: u64) -> PixelSpread {
        let mut env = config.make();
        let rendered: Vec<[u8; FRAME_BYTES]> = (0..frames)
            .map(|seed| {
                env.reset(seed).unwrap();
                let mut frame = [0u8; FRAME_BYTES];
                env.render(&mut frame);
                frame
            })
            .collect();
        PixelSpread::of_frames(rendered.iter().map(|f| &f[..]))
    }

    #[test]
    fn tridiagonal_solve_matches_a_hand_solved_system() {
        // [2 1 0; 1 3 1; 0 1 2] x = [3 5 3] has x = [1 1 1].
        let x = solve_tridiagonal(&[2.0, 3.0, 2.0], &[1.0, 1.0, 0.0], &[3.0, 5.0, 3.0]);
        for v in x {
            assert!((v - 1.0).abs() < 1e-12, "{v}");
        }
    }

    #[test]
    fn a_spread_that_depends_on_distance_alone_has_its_hub_where_it_was_drawn() {
        let centre = [37.25, 28.5];
        let std = (0..FRAME_PX * FRAME_PX)
            .map(|p| {
                let r = pixel_distance(p, centre);
                // Quiet at the hub, busiest 6 pixels out, fading with distance.
                if r < 2.0 {
                    0.0
                } else {
                    50.0 * (-(r - 6.0).powi(2) / 40.0).exp()
                }
            })
            .collect();
        let hub = PixelSpread { std }.hub().expect("a hub");
        let [col, row] = hub.pixels();
        assert!(
            (col - 37.25).abs() <= 0.25 && (row - 28.5).abs() <= 0.25,
            "{col} {row}"
        );
        assert!(hub.radial_r2 > 0.99, "{hub:?}");
        assert!(hub.core_share < 0.01, "{hub:?}");
    }

    #[test]
    fn frames_that_never_change_have_no_hub() {
        let frame = [90u8; FRAME_BYTES];
        let spread = PixelSpread::of_frames(std::iter::repeat_n(&frame[..], 4));
        assert_eq!(spread.hub(), None);
    }

    /// The cut lies in the sector the reacher's links never sweep (shoulder limits +-160
    /// degrees: the 40 degrees about the base's -x direction), wherever within a pixel of the
    /// base the hub is placed.
    #[test]
    fn the_quietest_direction_about_an_arms_base_is_its_unswept_sector_and_holds_still() {
        let reacher = ReacherConfig {
            base_m: [0.035, -0.025],
            ..Default::default()
        };
        let (col, row) = reacher.camera.project(reacher.base_m[0], reacher.base_m[1]);
        let (behind_col, behind_row) = reacher
            .camera
            .project(reacher.base_m[0] - 0.1, reacher.base_m[1]);
        let unswept = (behind_row - row).atan2(behind_col - col);
        let spread = spread_of(&EnvConfig::Reacher(reacher), 400);
        for (d_col, d_row) in [(0.0, 0.0), (0.3, 0.0), (-0.3, 0.0), (0.0, 0.3), (0.0, -0.3)] {
            let centre = image_point([col + d_col, row + d_row]);
            let [x, y] = spread.quietest_direction(centre);
            let off = (y.atan2(x) - unswept + std::f64::consts::PI)
                .rem_euclid(std::f64::consts::TAU)
                - std::f64::consts::PI;
            assert!(
                off.abs().to_degrees() <= 12.5,
                "centre moved ({d_col}, {d_row}) px: the cut is {:.1} degrees from the unswept \
                 sector's middle",
                off.to_degrees()
            );
        }
    }

    /// The reacher's hub is its base, at the image centre or moved off it; the point mass and
    /// Fetch have none.
    #[test]
    fn the_reachers_base_is_a_hub_and_the_point_mass_and_fetch_have_none() {
        let base_m = [0.035, -0.025];
        for config in [
            EnvConfig::from(EnvKind::Reacher),
            EnvConfig::Reacher(ReacherConfig {
                base_m,
                ..Default::default()
            }),
        ] {
            let EnvConfig::Reacher(reacher) = &config else {
                unreachable!()
            };
            let (col, row) = reacher.camera.project(reacher.base_m[0], reacher.base_m[1]);
            let hub = spread_of(&config, 400).hub().expect("the base is a hub");
            let [found_col, found_row] = hub.pixels();
            assert!(
                (found_col - col).abs() <= 1.0 && (found_row - row).abs() <= 1.0,
                "found ({found_col}, {found_row}), base at ({col}, {row}): {hub:?}"
            );
        }
        for kind in [EnvKind::PointMass, EnvKind::Fetch] {
            let hub = spread_of(&EnvConfig::from(kind), 400).hub();
            assert_eq!(hub, None, "{kind}");
        }
    }
}
