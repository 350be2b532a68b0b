//! The per-step update of the evidence grid: motion, decay, the points' votes and contacts.

use super::*;

impl ObstacleMemory {
    /// One step: move by the odometry `odo` held over `dt` seconds, decay, then add the `points`
    /// seen at the new pose (robot frame). In a step whose pair was not
    /// [`measurable`](Self::measurable) the points are ignored, so nothing is seen through: the
    /// cells in view fade at the `half_life_aside_s` rate, those out of view at theirs. (Fading
    /// the cells in view at the slower out-of-view rate too, or holding them down to a lower
    /// threshold, kept phantoms in front of a robot that stands or turns: fewer missions
    /// arrived.)
    pub fn update(&mut self, odo: BodyVelocity, dt: f64, points: &[SurfacePoint], measurable: bool) {
        if dt.is_finite() && dt > 0.0 && odo.v.is_finite() && odo.omega.is_finite() {
            let mid = self.pose.yaw + 0.5 * odo.omega * dt;
            self.pose.x += odo.v * dt * mid.cos();
            self.pose.y += odo.v * dt * mid.sin();
            self.pose.yaw = crate::pafsis::map::wrap_angle(self.pose.yaw + odo.omega * dt);
            let p = self.params;
            let (k_view, k_aside) = (0.5f64.powf(dt / p.half_life_view_s), 0.5f64.powf(dt / p.half_life_aside_s));
            let driven = (odo.v * dt).abs();
            let k_contact = 0.5f64.powf(driven / p.contact_half_life_m + dt / p.contact_half_life_s);
            // out of view nothing can confirm or clear a cell: it fades as the dead-reckoned pose
            // drifts (with the motion), and slowly over time, not while the robot stands beside it
            let turned = (odo.omega * dt).abs();
            let k_out = 0.5f64.powf(driven / p.out_half_life_m + turned / p.out_half_life_rad + dt / p.out_half_life_s);
            let (half_fov, cell) = (self.half_fov_rad, p.cell_m);
            // what the camera measured along each bearing sector this step
            self.seen.resize_with(SECTORS, Vec::new);
            self.seen.iter_mut().for_each(Vec::clear);
            if measurable {
                for pt in points {
                    if let Some(k) = sector(pt.left.atan2(pt.forward), half_fov) {
                        self.seen[k].push((pt.forward.hypot(pt.left), pt.up));
                    }
                }
            }
            let (pose, seen, h) = (self.pose, &self.seen, self.camera_height_m);
            self.cells.retain(|&(i, j), c| {
                let [f, l] = robot_frame(pose, cell, (i, j));
                let range = f.hypot(l);
                // seen through: the camera measured a surface beyond the cell on its bearing, by a
                // ray that passes over the cell lower than the top of what is remembered there (a
                // ray to the far wall above a low box says nothing about the box)
                let in_view = view_sector(f, l, half_fov);
                let through = in_view.is_some_and(|k| {
                    seen[k].iter().any(|&(r, up)| r > range + p.cell_m * 2.0 && h + (up - h) * range / r < c.top_m)
                });
                let out_of_view = in_view.is_none();
                c.evidence *= match (c.contact, through) {
                    (true, _) => k_contact,
                    (false, true) => k_view,
                    (false, false) if out_of_view => k_out,
                    (false, false) => k_aside,
                };
                range <= p.max_range_m && c.evidence >= 0.05
            });
        }
        self.touched.clear();
        let full_px = self.params.vote_full_radial_px;
        for pt in points.iter().filter(|_| measurable) {
            let range = pt.forward.hypot(pt.left);
            if !(range >= self.params.min_range_m && range <= self.params.max_range_m) {
                continue;
            }
            let key = self.cell_at(pt.forward, pt.left);
            let vote = if full_px > 0.0 { (pt.radial_px / full_px).clamp(0.0, 1.0) } else { 1.0 };
            self.touched.push((key, pt.up, vote));
        }
        // one vote per cell (its points' votes summed, at most 1), with its highest point; a
        // total order, so the sums are added in the same order on every run
        self.touched.sort_unstable_by(|a, b| a.0.cmp(&b.0).then(b.1.total_cmp(&a.1)).then(a.2.total_cmp(&b.2)));
        for cell in self.touched.chunk_by(|a, b| a.0 == b.0) {
            let (key, up, _) = cell[0];
            let vote: f64 = cell.iter().map(|t| t.2).sum();
            let c =
                self.cells.entry(key).or_insert(Cell { evidence: 0.0, contact: false, confirmed: false, top_m: up });
            c.evidence = (c.evidence + vote.min(1.0)).min(self.params.max_evidence);
            c.confirmed |= c.evidence >= self.params.occupied;
            c.top_m = c.top_m.max(up);
        }
    }

    /// Records a contact the camera could not see (the robot stalled while driving forward):
    /// the cells on an arc of `±half_arc_rad` just in front of the robot's footprint become
    /// solid, so that the path ahead reads blocked and the robot steers around what it touched.
    /// They fade with the distance driven (`contact_half_life_m`) and slowly with time
    /// (`contact_half_life_s`), not like what the camera saw: the robot is still beside what it
    /// touched when it turns back toward the goal, and turning back into it again and again
    /// was the stall loop.
    pub fn mark_contact(&mut self, half_arc_rad: f64) {
        let p = self.params;
        let r = p.robot_radius_m + 0.5 * p.cell_m;
        // one point per half cell along the arc
        let n = ((half_arc_rad.abs() * r) / (0.5 * p.cell_m)).ceil() as i32;
        for k in -n..=n {
            let b = if n == 0 { 0.0 } else { half_arc_rad.abs() * k as f64 / n as f64 };
            let key = self.cell_at(r * b.cos(), r * b.sin());
            // as tall as anything: no ray clears a contact
            self.cells
                .insert(key, Cell { evidence: p.max_evidence, contact: true, confirmed: true, top_m: f64::INFINITY });
        }
    }
}
