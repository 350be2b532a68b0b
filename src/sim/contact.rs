//! The `flownav::sim::contact` trace: at each new contact, what the obstacle memory held of the
//! object touched, and what the pipeline decided. It sorts contacts into "drove into something
//! it remembered" and "drove into something it had forgotten or never known" (docs/sim.md). A
//! cell is on an obstacle within [`GHOST_M`] of its footprint, as for the held score.

use super::quality::GHOST_M;
use crate::mofis::memory::ObstacleMemory;
use crate::step::{Pipeline, StepOutput};
use hal::BodyVelocity;
use mocks::world::Clearance;
use mocks::{Pose, World};

/// What the trace keeps between contacts.
pub(super) struct ContactTrace {
    /// Per obstacle ([`World::obstacle_distances`]' order): when the memory last held an
    /// occupied cell on it, s; −∞ while it never has.
    held_at: Vec<f64>,
    /// Contacts counted so far by the simulated base.
    contacts: u64,
}

/// One step of the mission, as the trace sees it.
pub(super) struct Scene<'a> {
    pub t_s: f64,
    /// The true pose.
    pub pose: Pose,
    pub world: &'a World,
    pub pipeline: &'a Pipeline,
    /// The pipeline's last output (the set-point in force).
    pub last: Option<&'a StepOutput>,
    pub odometry: BodyVelocity,
}

impl ContactTrace {
    /// `None` unless the trace is enabled.
    pub(super) fn new(world: &World) -> Option<Self> {
        tracing::enabled!(target: "flownav::sim::contact", tracing::Level::TRACE)
            .then(|| Self { held_at: vec![f64::NEG_INFINITY; world.boxes.len() + world.cylinders.len()], contacts: 0 })
    }

    /// After a step at `t_s` with the robot at `pose`: which obstacles `memory` holds an
    /// occupied cell on.
    pub(super) fn observe(&mut self, t_s: f64, pose: Pose, world: &World, memory: &ObstacleMemory) {
        let cells: Vec<[f64; 2]> = memory.occupied().into_iter().map(|c| pose.transform(c)).collect();
        for row in world.obstacle_distances(&cells) {
            for (held, d) in self.held_at.iter_mut().zip(row) {
                if d < GHOST_M {
                    *held = t_s;
                }
            }
        }
    }

    /// Before a step: one trace line if the base counted a new contact (`near`: what is
    /// nearest the robot now).
    pub(super) fn check(&mut self, contacts: u64, near: &Clearance, s: &Scene) {
        if contacts <= self.contacts {
            return;
        }
        self.contacts = contacts;
        let held_at = near.obstacle.and_then(|k| self.held_at.get(k)).copied().unwrap_or(f64::NEG_INFINITY);
        // every cell kept (down to 0.05): the occupied ones, and what is left below the threshold
        let memory = s.pipeline.memory();
        let occupied = memory.params().occupied;
        let cells = memory.cells_above(0.05);
        let on_near_object = |c: [f64; 2]| {
            let [x, y] = s.pose.transform(c);
            let at = s.world.clearance(x, y);
            at.object == near.object && at.distance_m < GHOST_M
        };
        let polar = |c: [f64; 2]| format!("{:.2}@{:.2}", c[0].hypot(c[1]), c[1].atan2(c[0]));
        let on_object: Vec<String> =
            cells.iter().filter(|(c, e, _)| *e >= occupied && on_near_object(*c)).map(|(c, ..)| polar(*c)).collect();
        let faint: Vec<String> = cells
            .iter()
            .filter(|(c, e, _)| *e < occupied && on_near_object(*c))
            .map(|(c, e, confirmed)| format!("{}:{e:.2}{}", polar(*c), if *confirmed { "*" } else { "" }))
            .collect();
        let held = cells.iter().filter(|(_, e, _)| *e >= occupied).count();
        let decided = s.last.map_or(String::new(), |o| {
            format!(
                "goal_v={:.2} goal_a={:.2} steer_a={:.2} avoid_d={:.2?} avoid_b={:.2?} weight={:.2} set_v={:.2} set_w={:.2}",
                o.goal.velocity,
                o.goal.angle_rad,
                o.steered.angle_rad,
                o.avoided.distance_m,
                o.avoided.bearing_rad,
                o.mofis.weight,
                o.mofis.setpoint.v,
                o.mofis.setpoint.omega
            )
        });
        tracing::trace!(
            target: "flownav::sim::contact",
            "contact t={:.2} x={:.2} y={:.2} yaw={:.2} object={} at={:.2} held_ago={:.2} odo_v={:.2} odo_w={:.2} occupied={} on_object=[{}] faint=[{}] {decided}",
            s.t_s,
            s.pose.x,
            s.pose.y,
            s.pose.yaw,
            near.object,
            contact_bearing(s.world, s.pose),
            s.t_s - held_at,
            s.odometry.v,
            s.odometry.omega,
            held,
            on_object.join(" "),
            faint.join(" ")
        );
    }
}

/// Where on the body a contact is: the bearing (rad from the heading, + = left) of the point of
/// the robot's rim nearest to anything, in 126 steps round the rim.
fn contact_bearing(world: &World, pose: Pose) -> f64 {
    let (r, n) = (super::ROBOT_RADIUS_M, 126);
    (0..n)
        .map(|k| -std::f64::consts::PI + k as f64 * std::f64::consts::TAU / n as f64)
        .map(|b| {
            let [x, y] = pose.transform([r * b.cos(), r * b.sin()]);
            (world.clearance(x, y).distance_m, b)
        })
        .fold((f64::INFINITY, 0.0), |a, c| if c.0 < a.0 { c } else { a })
        .1
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_contact_bearing_is_the_side_of_the_rim_that_touches() {
        // the office world's person, touched at the rim's point 1 rad to the right of the heading
        let world = World::office();
        let person = &world.cylinders[0];
        let (heading, at) = (0.7f64, -1.0f64);
        let reach = person.radius + super::super::ROBOT_RADIUS_M;
        let [px, py] = person.center;
        let pose = Pose::new(px - reach * (heading + at).cos(), py - reach * (heading + at).sin(), heading);
        assert!(world.clearance(pose.x, pose.y).obstacle == Some(world.boxes.len()), "touching the person");
        let b = contact_bearing(&world, pose);
        assert!((b - at).abs() <= std::f64::consts::TAU / 126.0, "{b}");
    }
}
