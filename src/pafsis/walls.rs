//! A corridor's side walls as landmarks (paper §2.2: the robot localises from what it
//! recognises). Dead reckoning's heading drifts with every turn a base makes a little short or
//! long and with wheels that are not quite equal (`flownav sim --odometry-error`), and a heading
//! error of a few degrees puts the robot against a wall within one corridor. A side wall that
//! OFFIS fits as a straight line runs along the corridor, so its direction in the robot's frame
//! says how the robot is turned against the corridor, and its distance, with the map's width,
//! says how far the robot is off the centre line.
//!
//! How well OFFIS's fits serve this is measured in docs/results.md: their distances follow the
//! offset; at 320×180 their directions follow the heading only weakly.
//!
//! Pure: sightings in, innovations out; [`super::Pafsis`] applies them with a small gain per
//! frame (a few seconds of agreeing frames move the estimate; one wrong frame hardly does).

use serde::Serialize;

/// A straight wall OFFIS fitted in the last frame pair, in the robot's frame (x forward, y left,
/// origin the robot's reference point), m.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct WallSighting {
    /// A point on the wall.
    pub point_m: [f64; 2],
    /// The wall's unit direction.
    pub dir: [f64; 2],
    /// How much of the wall the fit spans, m.
    pub length_m: f64,
    /// Up to two openings in the wall (doors), nearest first: their jambs, right one first.
    pub openings: [Option<[[f64; 2]; 2]>; 2],
}

impl WallSighting {
    /// The wall's direction relative to the robot's heading, folded into (−π/2, π/2], rad.
    pub fn angle_rad(&self) -> f64 {
        let a = self.dir[1].atan2(self.dir[0]);
        if a > std::f64::consts::FRAC_PI_2 {
            a - std::f64::consts::PI
        } else if a <= -std::f64::consts::FRAC_PI_2 {
            a + std::f64::consts::PI
        } else {
            a
        }
    }

    /// How much the heading relative to the corridor that this wall says (a wall along the
    /// corridor appears turned by minus the robot's heading against it) exceeds
    /// `heading_rel_rad`, the estimate's, rad.
    pub fn heading_disagreement(&self, heading_rel_rad: f64) -> f64 {
        -self.angle_rad() - heading_rel_rad
    }

    /// The sine of the angle at which the ray from the robot to `p` (a point on the wall, in
    /// the robot's frame) meets the wall: 0 grazing along it, 1 square on.
    pub fn sin_angle_to(&self, p: [f64; 2]) -> f64 {
        let r = p[0].hypot(p[1]);
        if r <= f64::EPSILON {
            return 0.0;
        }
        (p[0] * self.dir[1] - p[1] * self.dir[0]).abs() / r
    }

    /// The centres of the wall's openings that are a door's width (jamb to jamb,
    /// `DOOR_WIDTH_M`), ahead, and seen steeply enough to be placed along the wall (the sine of
    /// the angle at which the ray to the centre meets the wall, `DOOR_MIN_SIN`), m.
    pub fn door_openings(&self) -> impl Iterator<Item = [f64; 2]> + '_ {
        self.openings.iter().flatten().filter_map(|[a, b]| {
            let width = (a[0] - b[0]).hypot(a[1] - b[1]);
            let centre = [0.5 * (a[0] + b[0]), 0.5 * (a[1] + b[1])];
            (DOOR_WIDTH_M.contains(&width) && centre[0] > 0.0 && self.sin_angle_to(centre) >= DOOR_MIN_SIN)
                .then_some(centre)
        })
    }

    /// Signed distance from the robot to the wall's line, m: + when the wall is on the left.
    pub fn offset_m(&self) -> f64 {
        let [ux, uy] = self.dir;
        let [cx, cy] = self.point_m;
        // The line's foot point nearest the robot.
        let t = cx * ux + cy * uy;
        let (px, py) = (cx - t * ux, cy - t * uy);
        px.hypot(py).copysign(py)
    }
}

/// An opening in a wall this wide, jamb to jamb, is a door, m.
const DOOR_WIDTH_M: std::ops::RangeInclusive<f64> = 0.55..=1.1;
/// An opening counts as a door while the ray to its centre meets the wall at least this
/// steeply (the sine of 14°, tan 0.25): at a shallower angle, one profile bin (3.4° of the
/// C310's view) moves a jamb along the wall by more than a third of a metre. The angle is the
/// ray's against the wall, not against the robot's heading: a robot turned toward the wall
/// (swerving round a box) sees a door near the view's axis, yet steeply enough to place it.
const DOOR_MIN_SIN: f64 = 0.2425;

/// Which walls count, and how far a sighting may disagree with the estimate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WallGates {
    /// Shortest wall that counts, m: a box's face or a door jamb is shorter.
    pub min_length_m: f64,
    /// Largest heading disagreement a sighting may correct, rad.
    pub heading_gate_rad: f64,
    /// Largest lateral disagreement a sighting may correct, m.
    pub lateral_gate_m: f64,
}

impl Default for WallGates {
    fn default() -> Self {
        Self { min_length_m: 1.2, heading_gate_rad: 0.2, lateral_gate_m: 0.35 }
    }
}

/// What the side walls of one frame say against the estimate.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct WallInnovation {
    /// Measured minus estimated heading relative to the corridor, rad (mean over the walls).
    pub heading_rad: Option<f64>,
    /// Measured minus estimated offset left of the centre line, m.
    pub lateral_m: Option<f64>,
}

/// Compares the side walls among `walls` with the estimate: `heading_rel_rad` is the estimated
/// heading minus the corridor's direction, `left_m` the estimated offset left of the centre
/// line and `half_width_m` half the corridor's width (both only where the map gives them).
pub fn innovation(
    walls: &[WallSighting],
    heading_rel_rad: f64,
    lane: Option<(f64, f64)>,
    gates: &WallGates,
) -> WallInnovation {
    let (mut heading_sum, mut heading_n) = (0.0, 0u32);
    let (mut lateral_sum, mut lateral_n) = (0.0, 0u32);
    for w in walls.iter().filter(|w| w.length_m >= gates.min_length_m) {
        let d_heading = w.heading_disagreement(heading_rel_rad);
        if d_heading.abs() > gates.heading_gate_rad {
            continue;
        }
        heading_sum += d_heading;
        heading_n += 1;
        if let Some((left_m, half_width_m)) = lane {
            // Perpendicular to the wall, so the robot's heading does not enter.
            let off = w.offset_m();
            let measured_left = off.signum() * (half_width_m - off.abs());
            let d_left = measured_left - left_m;
            if d_left.abs() <= gates.lateral_gate_m {
                lateral_sum += d_left;
                lateral_n += 1;
            }
        }
    }
    WallInnovation {
        heading_rad: (heading_n > 0).then(|| heading_sum / f64::from(heading_n)),
        lateral_m: (lateral_n > 0).then(|| lateral_sum / f64::from(lateral_n)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Point `p` of the corridor frame in the frame of a robot at (0, `left`) turned `psi`.
    fn to_robot(psi: f64, left: f64, p: [f64; 2]) -> [f64; 2] {
        let (s, c) = psi.sin_cos();
        let (dx, dy) = (p[0], p[1] - left);
        [c * dx + s * dy, -s * dx + c * dy]
    }

    /// A side wall of a corridor `half` m half-wide, seen by a robot `left` m left of the centre
    /// line and turned `psi` against the corridor's direction.
    fn side_wall(psi: f64, left: f64, half: f64, on_left: bool) -> WallSighting {
        // Corridor frame: the wall is the line y = ±half; the robot at (0, left), heading psi.
        let y_wall = if on_left { half } else { -half };
        let a = to_robot(psi, left, [1.0, y_wall]);
        let b = to_robot(psi, left, [3.0, y_wall]);
        let n = (b[0] - a[0]).hypot(b[1] - a[1]);
        WallSighting { point_m: a, dir: [(b[0] - a[0]) / n, (b[1] - a[1]) / n], length_m: 2.0, openings: [None; 2] }
    }

    #[test]
    fn a_side_wall_gives_the_heading_and_the_offset() {
        let gates = WallGates::default();
        for on_left in [true, false] {
            let w = side_wall(0.08, 0.3, 1.0, on_left);
            assert!((w.angle_rad() + 0.08).abs() < 1e-12, "{}", w.angle_rad());
            let expect_off = if on_left { 0.7 } else { -1.3 };
            assert!((w.offset_m() - expect_off).abs() < 1e-12, "{} {}", w.offset_m(), expect_off);
            // The estimate believes: heading 0.02 off, 0.1 m left of the centre line.
            let i = innovation(&[w], 0.02, Some((0.1, 1.0)), &WallGates { lateral_gate_m: 1.0, ..gates });
            assert!((i.heading_rad.unwrap() - 0.06).abs() < 1e-12, "{i:?}");
            assert!((i.lateral_m.unwrap() - 0.2).abs() < 1e-12, "{i:?}");
        }
    }

    #[test]
    fn the_angle_at_a_wall_is_the_ray_against_the_wall_not_against_the_heading() {
        // A side wall 1 m to the right, a door's centre 3 m along it from abeam.
        for psi in [0.0, -0.3] {
            // the robot turned `psi` (toward the right wall when negative)
            let w = side_wall(psi, 0.0, 1.0, false);
            let p = to_robot(psi, 0.0, [3.0, -1.0]);
            let expect = (1.0f64).atan2(3.0).sin();
            assert!((w.sin_angle_to(p) - expect).abs() < 1e-12, "{psi}: {}", w.sin_angle_to(p));
        }
        // square on, and a degenerate point at the robot
        let frontal = WallSighting { point_m: [2.0, 0.0], dir: [0.0, 1.0], length_m: 2.0, openings: [None; 2] };
        assert!((frontal.sin_angle_to([2.0, 0.0]) - 1.0).abs() < 1e-12);
        assert_eq!(frontal.sin_angle_to([0.0, 0.0]), 0.0);
    }

    #[test]
    fn a_door_is_placed_by_the_angle_at_the_wall_even_near_the_view_axis() {
        // The right wall 0.9 m away, a 0.9 m door whose centre is `along` m ahead along it.
        let door = |psi: f64, along: f64| {
            let mut w = side_wall(psi, -0.1, 1.0, false);
            let jamb = |x: f64| to_robot(psi, -0.1, [x, -1.0]);
            w.openings[0] = Some([jamb(along + 0.45), jamb(along - 0.45)]);
            w
        };
        // Square to the corridor the door is 18° to the right, and its ray meets the wall at
        // 18°: a door.
        let square = door(0.0, 2.7);
        let [centre] = square.door_openings().collect::<Vec<_>>()[..] else { panic!("{square:?}") };
        assert!((centre[0] - 2.7).abs() < 1e-9 && (centre[1] + 0.9).abs() < 1e-9, "{centre:?}");
        // Swerving 17° toward the wall (round a box) the door is 1° off the view's axis, where
        // a bearing test would drop it, yet its ray still meets the wall at 18°: the same door.
        let turned = door(-0.3, 2.7);
        let [centre] = turned.door_openings().collect::<Vec<_>>()[..] else { panic!("{turned:?}") };
        assert!(centre[1].atan2(centre[0]).abs() < 0.03, "{centre:?}");
        assert!((centre[0].hypot(centre[1]) - 2.7f64.hypot(0.9)).abs() < 1e-9);
        // 5 m along, the ray grazes the wall at 10°, however the robot is turned: not placed.
        for psi in [0.0, -0.3, 0.3] {
            assert_eq!(door(psi, 5.0).door_openings().count(), 0, "{psi}");
        }
        // Too wide for a door (a gap between two boxes), or behind: no door.
        let mut wide = door(0.0, 2.7);
        wide.openings[0] = Some([[3.6, -0.9], [2.2, -0.9]]);
        wide.openings[1] = Some([[-0.4, -0.9], [-1.3, -0.9]]);
        assert_eq!(wide.door_openings().count(), 0);
    }

    #[test]
    fn short_walls_and_disagreeing_ones_do_not_count() {
        let gates = WallGates::default();
        let mut short = side_wall(0.05, 0.0, 1.0, true);
        short.length_m = 0.6;
        assert_eq!(innovation(&[short], 0.0, Some((0.0, 1.0)), &gates), WallInnovation::default());
        // A frontal wall (an end wall, a box face across the corridor) is no side wall.
        let frontal = WallSighting { point_m: [2.0, 0.0], dir: [0.0, 1.0], length_m: 2.0, openings: [None; 2] };
        assert_eq!(innovation(&[frontal], 0.0, None, &gates).heading_rad, None);
        // A wall 0.5 m nearer than the corridor's width puts it (a row of boxes): heading yes, offset no.
        let near = side_wall(0.0, 0.5, 1.0, true);
        let i = innovation(&[near], 0.0, Some((0.0, 1.0)), &gates);
        assert_eq!(i.heading_rad, Some(0.0));
        assert_eq!(i.lateral_m, None);
    }
}
