//! The located surface points of the last step, for the obstacle memory
//! ([`crate::mofis::memory`]): every block whose depth OFFIS measured reliably and that stands
//! above the floor, whatever it belongs to (TPO plane or obstacle). Collision avoidance needs
//! them all: a wall the robot is heading into is as solid as a box.

use super::Offis;
use super::features::TOP_M;

/// Rays closer than this to the direction of travel give no surface points, rad: there the true
/// radial flow is small and a matching error of a fraction of a pixel places a phantom surface
/// right in front of the robot. An obstacle in the path is found by its edges, which lie
/// farther out (a 0.4 m wide box 1.5 m ahead: 0.13 rad).
pub const MIN_OFF_AXIS_RAD: f64 = 0.08;

/// One located point on the floor plan, robot frame at the newer frame (REP-103, origin on the
/// floor between the wheels), m.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    pub forward: f64,
    pub left: f64,
    /// Height above the floor, m.
    pub up: f64,
    /// The block's radial flow, pixels per frame interval: the depth of a point from `ρ` px is
    /// off by about `σ/ρ` for a matching noise `σ`, so this is how much the point is worth.
    pub radial_px: f64,
}

impl Offis {
    /// The points of the last [`Offis::step`] that are solid for the robot: located (the robot
    /// was translating), higher than the floor test of the obstacle decision
    /// (`max(depth.floor_height_m, depth.floor_rel · camera height)`), below [`TOP_M`] (not the
    /// ceiling or a lintel), with radial flow of at least `depth.reliable_radial_px`.
    /// `mount_m` is the camera's mount (x ahead, y left, z up), to move the points from the
    /// optical centre to the robot's origin. `min_radial_px` raises the radial-flow floor (a
    /// depth from `ρ` px of radial flow with matching noise `σ` is off by about `σ/ρ`; one
    /// mismatched block in a frame must not become a wall in front of the robot) and
    /// `max_tangential` bounds the tangential flow as a fraction of the radial one.
    pub fn surface_points(
        &self,
        mount_m: [f64; 3],
        min_radial_px: f64,
        max_tangential: f64,
        out: &mut Vec<SurfacePoint>,
    ) {
        out.clear();
        let p = &self.params.depth;
        let z_m = mount_m[2];
        let floor_m = p.floor_height_m.max(p.floor_rel * z_m);
        for l in self.located.iter().flatten() {
            let up = l.up + z_m;
            // near the focus of expansion any flow error reads as radial flow: skip rays within
            // MIN_OFF_AXIS_RAD of the direction of travel
            if l.left.hypot(l.up).atan2(l.forward) < MIN_OFF_AXIS_RAD {
                continue;
            }
            if up >= floor_m
                && up <= TOP_M
                && l.radial_px >= p.reliable_radial_px.max(min_radial_px)
                && l.tangential_px <= max_tangential * l.radial_px
            {
                out.push(SurfacePoint {
                    forward: l.forward + mount_m[0],
                    left: l.left + mount_m[1],
                    up,
                    radial_px: l.radial_px,
                });
            }
        }
    }
}
