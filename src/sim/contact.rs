//! What the obstacle memory knew of the object the robot touched.
//!
//! [`classify`] sorts the first contact of every run (the summary's `first_contact.memory`):
//! the memory held the object as occupied, held it only as cells the footprint guard counts,
//! held guard-strength cells near the contact but off the object, had let it fade below the
//! guard, or knew nothing. Each class calls for a different remedy (the avoidance, the guard,
//! the depth of the cells, the fade), so a tally over many runs says which design to try.
//!
//! The `flownav::sim::contact` trace prints, at each new contact, the cells behind that class
//! and what the pipeline decided (docs/sim.md). A cell is on an obstacle within [`GHOST_M`] of
//! its footprint, as for the held score.

use super::quality::GHOST_M;
use crate::mofis::memory::ObstacleMemory;
use crate::step::{Pipeline, StepOutput};
use hal::BodyVelocity;
use mocks::world::Clearance;
use mocks::{Pose, World};
use serde::Serialize;

/// Cells the guard counts this near the robot, m, and this near the contact's bearing, rad, off
/// every surface, make a contact [`ContactMemory::Misplaced`] when none is on the object: the
/// obstacle's corner reaching the rim while the memory holds its face a few decimetres off.
const NEAR_M: f64 = 1.0;
const NEAR_RAD: f64 = 1.0;

/// A cell counts as holding the touched part of the object within this of the point of the rim
/// that touched, m: a box held only at its far end has been forgotten where it matters.
const AT_CONTACT_M: f64 = 0.3;

/// What the memory held of the touched object at the contact, the first class that applies.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ContactMemory {
    /// An occupied cell on the touched part of the object (within `AT_CONTACT_M` of the point of
    /// the rim that touched): the avoidance knew it and still drove there.
    Occupied,
    /// Cells on the touched part that the footprint guard counts, none occupied.
    Guarded,
    /// No guard-strength cell on the touched part, but some near the robot on the contact's
    /// side, off every surface (where the object is not).
    Misplaced,
    /// Cells on the touched part, all below what the guard counts: the memory let it fade.
    Faded,
    /// Nothing on the touched part and nothing near: never seen, or forgotten (held, if at
    /// all, only at its far end).
    Unknown,
}

/// Where on the rim the robot at `pose` touches `object` (rad from the heading) and what the
/// pipeline's memory holds of it, by the pipeline's own thresholds.
pub(super) fn at_contact(pipeline: &Pipeline, world: &World, pose: Pose, object: &str) -> (f64, ContactMemory) {
    let at_rad = contact_bearing(world, pose);
    let memory = pipeline.memory();
    let cells: Vec<([f64; 2], f64)> = memory.cells_above(0.05).into_iter().map(|(c, e, _)| (c, e)).collect();
    let occupied = memory.params().occupied;
    // with the guard off, what it would count is what the avoidance counts
    let guard = Some(pipeline.mofis().params().guard_evidence).filter(|g| *g > 0.0).unwrap_or(occupied);
    (at_rad, classify(&cells, occupied, guard, world, pose, object, at_rad))
}

/// What the memory held of `object` (a [`World::clearance`] label) when the robot, at `pose`,
/// touched it at `at_rad` from its heading. `cells`: the memory's cells in the robot frame with
/// their evidence; `occupied` and `guard`: the evidence of an occupied cell and the least the
/// guard counts.
pub fn classify(
    cells: &[([f64; 2], f64)],
    occupied: f64,
    guard: f64,
    world: &World,
    pose: Pose,
    object: &str,
    at_rad: f64,
) -> ContactMemory {
    let rim = [super::ROBOT_RADIUS_M * at_rad.cos(), super::ROBOT_RADIUS_M * at_rad.sin()];
    let on_object = |c: [f64; 2]| {
        let [x, y] = pose.transform(c);
        let at = world.clearance(x, y);
        at.object == object && at.distance_m < GHOST_M && (c[0] - rim[0]).hypot(c[1] - rim[1]) <= AT_CONTACT_M
    };
    let on: Vec<f64> = cells.iter().filter(|(c, _)| on_object(*c)).map(|(_, e)| *e).collect();
    let off_surfaces = |c: [f64; 2]| {
        let [x, y] = pose.transform(c);
        world.clearance(x, y).distance_m >= GHOST_M
    };
    let near = |c: [f64; 2]| {
        let off =
            (c[1].atan2(c[0]) - at_rad + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
        c[0].hypot(c[1]) <= NEAR_M && off.abs() <= NEAR_RAD
    };
    if on.iter().any(|&e| e >= occupied) {
        ContactMemory::Occupied
    } else if on.iter().any(|&e| e >= guard) {
        ContactMemory::Guarded
    } else if cells.iter().any(|(c, e)| *e >= guard && near(*c) && off_surfaces(*c)) {
        ContactMemory::Misplaced
    } else if !on.is_empty() {
        ContactMemory::Faded
    } else {
        ContactMemory::Unknown
    }
}

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
        let (at_rad, class) = at_contact(s.pipeline, s.world, s.pose, &near.object);
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
            "contact t={:.2} x={:.2} y={:.2} yaw={:.2} object={} at={:.2} memory={class:?} held_ago={:.2} odo_v={:.2} odo_w={:.2} occupied={} on_object=[{}] faint=[{}] {decided}",
            s.t_s,
            s.pose.x,
            s.pose.y,
            s.pose.yaw,
            near.object,
            at_rad,
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
        let (world, pose, _, at) = touching_the_person();
        assert!(world.clearance(pose.x, pose.y).obstacle == Some(world.boxes.len()), "touching the person");
        let b = contact_bearing(&world, pose);
        assert!((b - at).abs() <= std::f64::consts::TAU / 126.0, "{b}");
    }

    /// The office's person touched at the rim's point 1 rad to the right of the heading: the
    /// world, the robot's pose, the person's label and the contact's bearing.
    fn touching_the_person() -> (World, Pose, String, f64) {
        let world = World::office();
        let person = &world.cylinders[0];
        let (heading, at) = (0.7f64, -1.0f64);
        let reach = person.radius + super::super::ROBOT_RADIUS_M;
        let [px, py] = person.center;
        let pose = Pose::new(px - reach * (heading + at).cos(), py - reach * (heading + at).sin(), heading);
        let object = world.clearance(pose.x, pose.y).object;
        (world, pose, object, at)
    }

    /// A robot-frame point `r` m out at `b` rad.
    fn polar(r: f64, b: f64) -> [f64; 2] {
        [r * b.cos(), r * b.sin()]
    }

    #[test]
    fn a_contact_is_classed_by_what_the_memory_held_of_the_object() {
        let (world, pose, object, at) = touching_the_person();
        let on = polar(super::super::ROBOT_RADIUS_M + 0.03, at);
        let aside = polar(0.6, at + 0.8);
        let behind = polar(0.6, at + std::f64::consts::PI);
        for c in [aside, behind] {
            let [x, y] = pose.transform(c);
            assert!(world.clearance(x, y).distance_m >= GHOST_M, "{c:?} must be off every surface");
        }
        let class = |cells: &[([f64; 2], f64)]| classify(cells, 1.5, 0.3, &world, pose, &object, at);
        assert_eq!(class(&[(on, 2.0), (aside, 0.5)]), ContactMemory::Occupied);
        assert_eq!(class(&[(on, 0.5), (aside, 2.0)]), ContactMemory::Guarded);
        assert_eq!(class(&[(on, 0.1), (aside, 0.5)]), ContactMemory::Misplaced);
        assert_eq!(class(&[(on, 0.1), (aside, 0.2)]), ContactMemory::Faded);
        assert_eq!(class(&[(on, 0.1), (behind, 2.0)]), ContactMemory::Faded);
        assert_eq!(class(&[(behind, 2.0)]), ContactMemory::Unknown);
        // the person's far side, 0.5 m from the rim's point: held, but not where it touched
        let far = polar(super::super::ROBOT_RADIUS_M + 0.45, at);
        assert_eq!(class(&[(far, 2.0)]), ContactMemory::Unknown);
        assert_eq!(class(&[(far, 2.0), (on, 0.5)]), ContactMemory::Guarded);
        assert_eq!(class(&[]), ContactMemory::Unknown);
    }
}
