//! Missions: where the simulated drone flies and where its camera looks, and the same
//! pattern as a QGroundControl `.plan` an operator can fly for real.
//!
//! Area scenarios follow the area seed (sec. 4.2.4, fig. 4.12): waypoints along the
//! ground-truth border, offset horizontally away from the target area and swinging in
//! altitude, flown at a speed limit, with the gimbal on the nearest border point. The
//! indoor scenario flies a smooth Lissajous path over the floor with the small roll and
//! pitch a quadrotor has when it accelerates, camera fixed to the body looking down.

use std::f64::consts::{PI, TAU};

use mavloc_data::dataset::GimbalFrame;
use mavloc_geometry::{Bearing, GimbalAngles, LocalFrame, Vec3};
use serde::{Deserialize, Serialize};

use crate::scenario::{MissionPattern, WorldKind};
use crate::state::State;
use crate::world::World;

/// A flight: waypoints and a way to sample the state at any time.
#[derive(Clone, Debug)]
pub struct Mission {
    pub waypoints: Vec<Vec3>,
    /// Ground point each waypoint's camera looks at (region of interest).
    pub rois: Vec<Vec3>,
    pub speed: f64,
    pub frame_rate: f64,
    pub gimbal_frame: GimbalFrame,
    /// Cumulative path length at each waypoint.
    cumulative: Vec<f64>,
    border: Vec<Vec<Vec3>>,
    chain: mavloc_geometry::GimbalChain,
    floor_half: f64,
    altitude: f64,
    swing: f64,
    /// A photo survey's lines (from, to, metres along the path), where its frames are
    /// taken (not on the turns between lines nor the way home); empty around a border.
    /// A survey's camera looks straight down, top to the direction of flight.
    lines: Vec<(f64, f64)>,
}

impl Mission {
    /// Plans the scenario's mission in a built world.
    pub fn plan(world: &World) -> Result<Mission, String> {
        let s = &world.scenario;
        let m = &s.mission;
        let nadir = m.pattern == MissionPattern::Lines && s.kind != WorldKind::IndoorFloor;
        // Waypoint indices where each survey line starts and ends.
        let mut line_ends: Vec<(usize, usize)> = Vec::new();
        let (waypoints, rois, gimbal_frame) = match s.kind {
            WorldKind::Coastline | WorldKind::Cliff if nadir => {
                let ring = world
                    .ground_truth
                    .iter()
                    .max_by(|a, b| path_length(a).total_cmp(&path_length(b)))
                    .ok_or("the world has no ground-truth border to survey")?;
                let samples = resample(ring, m.waypoint_spacing_m.min(5.0));
                let k = (0..samples.len())
                    .max_by(|&a, &b| samples[a].x.total_cmp(&samples[b].x))
                    .ok_or("the border has no points")?;
                let p = samples[k];
                let along = (samples[(k + 1) % samples.len()]
                    - samples[(k + samples.len() - 1) % samples.len()])
                .normalize();
                let mut across = Vec3::new(-along.y, along.x, 0.0);
                if world.is_target(p.x + 2.0 * across.x, p.y + 2.0 * across.y) {
                    across = -across;
                }
                let mut wps = Vec::new();
                let mut ends = Vec::new();
                let mid = (m.line_count as f64 - 1.0) / 2.0;
                for i in 0..m.line_count {
                    let centre = p + across * ((i as f64 - mid) * m.line_spacing_m);
                    let half = along * (m.line_length_m / 2.0);
                    let (a, b) = if i % 2 == 0 {
                        (centre - half, centre + half)
                    } else {
                        (centre + half, centre - half)
                    };
                    // Waypoints every 5 m, so the path is flown straight at the speed limit.
                    let n = (m.line_length_m / 5.0).ceil().max(1.0) as usize;
                    ends.push((wps.len(), wps.len() + n));
                    for j in 0..=n {
                        let q = a + (b - a) * (j as f64 / n as f64);
                        wps.push(Vec3::new(q.x, q.y, -m.altitude_m));
                    }
                }
                let rois = wps.iter().map(|w| Vec3::new(w.x, w.y, 0.0)).collect();
                line_ends = ends;
                (wps, rois, GimbalFrame::Earth)
            }
            WorldKind::Coastline | WorldKind::Cliff => {
                let ring = world
                    .ground_truth
                    .iter()
                    .max_by(|a, b| path_length(a).total_cmp(&path_length(b)))
                    .ok_or("the world has no ground-truth border to fly along")?;
                let samples = resample(ring, m.waypoint_spacing_m);
                let mut wps = Vec::new();
                let mut rois = Vec::new();
                let mut along = 0.0;
                for (k, p) in samples.iter().enumerate() {
                    if k > 0 {
                        along += (p - samples[k - 1]).norm();
                    }
                    let next = samples[(k + 1) % samples.len()];
                    let prev = samples[(k + samples.len() - 1) % samples.len()];
                    let tangent = next - prev;
                    let mut normal = Vec3::new(-tangent.y, tangent.x, 0.0).normalize();
                    // Point away from the target area.
                    let probe = p + normal * 2.0;
                    if world.is_target(probe.x, probe.y) {
                        normal = -normal;
                    }
                    let alt = m.altitude_m + m.altitude_swing_m * (TAU * along / 160.0).sin();
                    let wp = p + normal * m.offset_m;
                    wps.push(Vec3::new(wp.x, wp.y, -alt));
                    rois.push(*p);
                }
                (wps, rois, GimbalFrame::Earth)
            }
            WorldKind::IndoorFloor => {
                // One Lissajous loop over the floor (3:2), 0.75 of the half-width.
                let a = 4.0 * 0.75;
                let wps: Vec<Vec3> = (0..120)
                    .map(|k| {
                        let t = TAU * k as f64 / 120.0;
                        Vec3::new(a * (3.0 * t).sin(), a * (2.0 * t + PI / 4.0).sin(), -m.altitude_m)
                    })
                    .collect();
                let rois = wps.iter().map(|w| Vec3::new(w.x, w.y, 0.0)).collect();
                (wps, rois, GimbalFrame::Body)
            }
        };
        if waypoints.len() < 3 {
            return Err("mission has fewer than 3 waypoints".into());
        }
        let mut cumulative = vec![0.0];
        for k in 1..=waypoints.len() {
            let d = (waypoints[k % waypoints.len()] - waypoints[k - 1]).norm();
            cumulative.push(cumulative[k - 1] + d);
        }
        let lines = line_ends.iter().map(|&(a, b)| (cumulative[a], cumulative[b])).collect();
        Ok(Mission {
            waypoints,
            rois,
            speed: m.speed_m_s,
            frame_rate: m.frame_rate_hz,
            gimbal_frame,
            cumulative,
            border: world.ground_truth.clone(),
            chain: s.camera.chain,
            floor_half: 4.0,
            altitude: m.altitude_m,
            swing: m.altitude_swing_m,
            lines,
        })
    }

    /// Length of one lap, metres.
    pub fn lap_length(&self) -> f64 {
        *self.cumulative.last().expect("non-empty")
    }

    /// Duration of one lap at the speed limit, seconds.
    pub fn duration(&self) -> f64 {
        self.lap_length() / self.speed
    }

    /// Frames in one lap at the capture rate.
    pub fn frame_count(&self) -> usize {
        self.frame_times().len()
    }

    /// When frames are taken, seconds from the start: every `1 / frame_rate` around a
    /// lap; on a survey, from the start of each line to its end at the same spacing.
    pub fn frame_times(&self) -> Vec<f64> {
        if self.lines.is_empty() {
            // Around a lap: one lap's worth, the lap's end (its start) not shot twice.
            let count = (self.lap_length() / self.speed * self.frame_rate).floor() as usize;
            return (0..count).map(|i| i as f64 / self.frame_rate).collect();
        }
        let step = self.speed / self.frame_rate;
        // A line is shot from a margin after its start to a margin before its end, so the
        // heading (from the velocity over +-0.05 s) is the line's, not the turn's.
        let margin = (0.1 * self.speed).max(0.5);
        let mut times = Vec::new();
        for &(from, to) in &self.lines {
            let (start, end) = (from + margin, to - margin);
            let shots = ((end - start) / step + 1e-9).floor().max(-1.0) as i64 + 1;
            times.extend((0..shots).map(|i| (start + i as f64 * step) / self.speed));
        }
        times
    }

    fn position_at(&self, t: f64) -> Vec3 {
        let s = (t * self.speed).rem_euclid(self.lap_length());
        let k = self.cumulative.partition_point(|&c| c <= s).saturating_sub(1).min(self.waypoints.len() - 1);
        let (a, b) = (self.waypoints[k], self.waypoints[(k + 1) % self.waypoints.len()]);
        let seg = self.cumulative[k + 1] - self.cumulative[k];
        let f = if seg > 0.0 { (s - self.cumulative[k]) / seg } else { 0.0 };
        a + (b - a) * f
    }

    /// The true state at time `t` seconds after the start.
    pub fn state(&self, t: f64) -> State {
        let dt = 0.05;
        let position = self.position_at(t);
        let velocity = (self.position_at(t + dt) - self.position_at(t - dt)) / (2.0 * dt);
        let heading = velocity.y.atan2(velocity.x);
        match self.gimbal_frame {
            GimbalFrame::Earth if !self.lines.is_empty() => {
                let gimbal = GimbalAngles { yaw: heading, pitch: -PI / 2.0, roll: 0.0 };
                State { t, position, velocity, attitude: [0.0, 0.0, heading], gimbal }
            }
            GimbalFrame::Earth => {
                let target = mavloc_geometry::nearest_on_polylines(&self.border, &position)
                    .map(|(q, _)| q)
                    .unwrap_or(Vec3::new(position.x, position.y, 0.0));
                let b = Bearing::from_direction(&(target - position))
                    .unwrap_or(Bearing { yaw: heading, pitch: -PI / 2.0 });
                let gimbal = GimbalAngles { yaw: b.yaw, pitch: b.pitch, roll: 0.0 };
                State { t, position, velocity, attitude: [0.0, 0.0, heading], gimbal }
            }
            GimbalFrame::Body => {
                // Tilt from acceleration (a quadrotor leans into it) plus a slow wobble;
                // yaw turns slowly so histograms meet every heading.
                // Over half a second, so waypoint corners do not read as jerks.
                let h = 0.5;
                let acc = (self.position_at(t + h) - position * 2.0 + self.position_at(t - h)) / (h * h);
                let g = 9.81;
                let yaw = 0.6 * (0.07 * t).sin() + 0.3 * t.sin() * 0.1;
                let (sy, cy) = yaw.sin_cos();
                // Body-frame acceleration: pitch forward (negative) to accelerate forward.
                let a_fwd = acc.x * cy + acc.y * sy;
                let a_right = -acc.x * sy + acc.y * cy;
                let pitch = (-a_fwd / g).atan() + 0.02 * (1.3 * t).sin();
                let roll = (a_right / g).atan() + 0.02 * (1.7 * t + 1.0).sin();
                let mut position = position;
                position.z = -(self.altitude + self.swing * (0.2 * t).sin());
                let position = Vec3::new(
                    position.x.clamp(-self.floor_half, self.floor_half),
                    position.y.clamp(-self.floor_half, self.floor_half),
                    position.z,
                );
                let gimbal = GimbalAngles { yaw: 0.0, pitch: -PI / 2.0, roll: 0.0 };
                State { t, position, velocity, attitude: [roll, pitch, yaw], gimbal }
            }
        }
    }

    /// The camera pose of a state.
    pub fn camera_pose(&self, s: &State) -> mavloc_geometry::CameraPose {
        use mavloc_geometry::{body_rotation, CameraPose, Mount};
        let mount = match self.gimbal_frame {
            GimbalFrame::Earth => Mount::Earth,
            GimbalFrame::Body => {
                Mount::Body { attitude: body_rotation(s.attitude[0], s.attitude[1], s.attitude[2]) }
            }
        };
        CameraPose::from_gimbal(s.position, self.chain, s.gimbal, mount)
    }

    /// The mission as a QGroundControl plan: takeoff, speed limit, a region of interest
    /// (MAV_CMD_DO_SET_ROI_LOCATION, which PX4's gimbal manager follows) before each
    /// waypoint, the waypoints (altitudes relative to home), ROI reset and return to launch.
    pub fn qgc_plan(&self, frame: &LocalFrame) -> QgcPlan {
        let home = frame.origin;
        let mut items = Vec::new();
        let mut id = 0;
        let mut push = |command: u16, frame_id: u8, params: [Option<f64>; 7], nav_alt: Option<f64>| {
            id += 1;
            items.push(QgcItem {
                item_type: "SimpleItem".into(),
                auto_continue: true,
                command,
                do_jump_id: id,
                frame: frame_id,
                params,
                altitude: nav_alt,
                altitude_mode: nav_alt.map(|_| 1),
            });
        };
        let first_alt = -self.waypoints[0].z;
        push(
            MAV_CMD_NAV_TAKEOFF,
            3,
            [Some(0.0), Some(0.0), Some(0.0), None, Some(home.lat_deg), Some(home.lon_deg), Some(first_alt)],
            Some(first_alt),
        );
        push(
            MAV_CMD_DO_CHANGE_SPEED,
            2,
            [Some(1.0), Some(self.speed), Some(-1.0), Some(0.0), Some(0.0), Some(0.0), Some(0.0)],
            None,
        );
        for (wp, roi) in self.waypoints.iter().zip(&self.rois) {
            let r = frame.to_geodetic(roi);
            let w = frame.to_geodetic(wp);
            let roi_alt = r.alt_m - home.alt_m;
            push(
                MAV_CMD_DO_SET_ROI_LOCATION,
                3,
                [Some(0.0), Some(0.0), Some(0.0), Some(0.0), Some(r.lat_deg), Some(r.lon_deg), Some(roi_alt)],
                None,
            );
            let alt = -wp.z;
            push(
                MAV_CMD_NAV_WAYPOINT,
                3,
                [Some(0.0), Some(0.0), Some(0.0), None, Some(w.lat_deg), Some(w.lon_deg), Some(alt)],
                Some(alt),
            );
        }
        push(MAV_CMD_DO_SET_ROI_NONE, 2, [Some(0.0); 7], None);
        push(MAV_CMD_NAV_RETURN_TO_LAUNCH, 2, [Some(0.0); 7], None);
        QgcPlan {
            file_type: "Plan".into(),
            version: 1,
            ground_station: "QGroundControl".into(),
            geo_fence: serde_json::json!({"circles": [], "polygons": [], "version": 2}),
            rally_points: serde_json::json!({"points": [], "version": 2}),
            mission: QgcMission {
                version: 2,
                firmware_type: 12, // MAV_AUTOPILOT_PX4
                vehicle_type: 2,   // MAV_TYPE_QUADROTOR
                cruise_speed: self.speed,
                hover_speed: self.speed,
                global_plan_altitude_mode: 1, // relative to home
                planned_home_position: [home.lat_deg, home.lon_deg, home.alt_m],
                items,
            },
        }
    }
}

pub const MAV_CMD_NAV_WAYPOINT: u16 = 16;
pub const MAV_CMD_NAV_RETURN_TO_LAUNCH: u16 = 20;
pub const MAV_CMD_NAV_TAKEOFF: u16 = 22;
pub const MAV_CMD_DO_CHANGE_SPEED: u16 = 178;
pub const MAV_CMD_DO_SET_ROI_LOCATION: u16 = 195;
pub const MAV_CMD_DO_SET_ROI_NONE: u16 = 197;

/// QGroundControl's plan file (the subset mavloc writes; QGC ignores nothing it needs).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct QgcPlan {
    #[serde(rename = "fileType")]
    pub file_type: String,
    pub version: u32,
    #[serde(rename = "groundStation")]
    pub ground_station: String,
    #[serde(rename = "geoFence")]
    pub geo_fence: serde_json::Value,
    #[serde(rename = "rallyPoints")]
    pub rally_points: serde_json::Value,
    pub mission: QgcMission,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct QgcMission {
    pub version: u32,
    #[serde(rename = "firmwareType")]
    pub firmware_type: u32,
    #[serde(rename = "vehicleType")]
    pub vehicle_type: u32,
    #[serde(rename = "cruiseSpeed")]
    pub cruise_speed: f64,
    #[serde(rename = "hoverSpeed")]
    pub hover_speed: f64,
    #[serde(rename = "globalPlanAltitudeMode")]
    pub global_plan_altitude_mode: u32,
    #[serde(rename = "plannedHomePosition")]
    pub planned_home_position: [f64; 3],
    pub items: Vec<QgcItem>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct QgcItem {
    #[serde(rename = "type")]
    pub item_type: String,
    #[serde(rename = "autoContinue")]
    pub auto_continue: bool,
    pub command: u16,
    #[serde(rename = "doJumpId")]
    pub do_jump_id: u32,
    pub frame: u8,
    /// Seven parameters; QGC writes NaN ("unchanged") as null.
    pub params: [Option<f64>; 7],
    #[serde(rename = "Altitude", skip_serializing_if = "Option::is_none", default)]
    pub altitude: Option<f64>,
    #[serde(rename = "AltitudeMode", skip_serializing_if = "Option::is_none", default)]
    pub altitude_mode: Option<u32>,
}

fn path_length(line: &[Vec3]) -> f64 {
    line.windows(2).map(|w| (w[1] - w[0]).norm()).sum()
}

/// Points every `spacing` metres along a polyline (a closed ring drops its repeated end).
fn resample(line: &[Vec3], spacing: f64) -> Vec<Vec3> {
    let closed = line.len() > 2 && line.first() == line.last();
    let pts = if closed { &line[..line.len() - 1] } else { line };
    let mut out = vec![pts[0]];
    let mut carry = 0.0;
    let n = if closed { pts.len() } else { pts.len() - 1 };
    for k in 0..n {
        let (a, b) = (pts[k], pts[(k + 1) % pts.len()]);
        let len = (b - a).norm();
        let mut s = spacing - carry;
        while s <= len {
            out.push(a + (b - a) * (s / len));
            s += spacing;
        }
        carry = len - (s - spacing);
    }
    if closed && out.len() > 1 && (out[out.len() - 1] - out[0]).norm() < spacing * 0.5 {
        out.pop();
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenario::Scenario;

    /// The photo survey: three parallel lines 30 m apart across the shore, the middle one
    /// flown back, photos only on the lines (none on the turns) every 12.5 m, the camera
    /// straight down with its top to the direction of flight.
    #[test]
    fn a_survey_flies_parallel_lines_with_the_camera_straight_down() {
        let world = World::build(&Scenario::load("coastline-survey").unwrap()).unwrap();
        let m = Mission::plan(&world).unwrap();
        let states: Vec<State> = m.frame_times().iter().map(|&t| m.state(t)).collect();
        assert_eq!(states.len(), 18, "6 photos on each of 3 lines of 65 m");
        let lines: Vec<&[State]> = states.chunks(6).collect();
        let dir = |l: &[State]| (l[5].position - l[0].position).normalize();
        for (i, line) in lines.iter().enumerate() {
            for w in line.windows(2) {
                assert!(((w[1].position - w[0].position).norm() - 12.5).abs() < 1e-6, "line {i}");
            }
            for s in line.iter() {
                assert!((s.position.z + 40.0).abs() < 1e-9);
                assert!((s.gimbal.pitch + std::f64::consts::FRAC_PI_2).abs() < 1e-12, "straight down");
                let heading = Vec3::new(s.gimbal.yaw.cos(), s.gimbal.yaw.sin(), 0.0);
                assert!(heading.dot(&dir(line)) > 0.9999, "top of the image to the direction of flight");
            }
        }
        assert!(dir(lines[0]).dot(&dir(lines[1])) < -0.9999, "the middle line is flown back");
        assert!(dir(lines[0]).dot(&dir(lines[2])) > 0.9999);
        // 30 m apart, across the lines.
        let across = |a: &State, b: &State| {
            let d = b.position - a.position;
            (d - dir(lines[0]) * d.dot(&dir(lines[0]))).norm()
        };
        assert!((across(&lines[0][0], &lines[1][0]) - 30.0).abs() < 1e-6);
        assert!((across(&lines[0][0], &lines[2][0]) - 60.0).abs() < 1e-6);
        // The middle line runs along the shore: it sees water and land.
        let middle = &lines[1][3];
        let (shore, _) = world.nearest_border_point(&middle.position).unwrap();
        assert!((shore - Vec3::new(middle.position.x, middle.position.y, shore.z)).norm() < 15.0);
    }

    #[test]
    fn coastline_mission_flies_outside_the_lake_and_looks_at_the_shore() {
        let world = World::build(&Scenario::load("coastline").unwrap()).unwrap();
        let m = Mission::plan(&world).unwrap();
        assert!(m.waypoints.len() > 20);
        for wp in &m.waypoints {
            assert!(!world.is_target(wp.x, wp.y), "waypoint over water at {wp:?}");
            assert!((-wp.z - 30.0).abs() <= 4.0 + 1e-9);
        }
        // At 3 m/s and 6 Hz the spacing between frames is 0.5 m.
        let (a, b) = (m.state(10.0), m.state(10.0 + 1.0 / 6.0));
        assert!(((b.position - a.position).norm() - 0.5).abs() < 0.05);
        // The camera looks at the border: it projects near the image centre.
        let k = world.scenario.intrinsics().downscaled(4);
        let pose = m.camera_pose(&a);
        let (target, _) = world.nearest_border_point(&a.position).unwrap();
        let px = pose.project(&k, &target).unwrap();
        assert!((px.u - k.cx).abs() < 1.0 && (px.v - k.cy).abs() < 1.0);
    }

    #[test]
    fn qgc_plan_round_trips_and_has_what_qgc_needs() {
        let world = World::build(&Scenario::load("cliff").unwrap()).unwrap();
        let m = Mission::plan(&world).unwrap();
        let plan = m.qgc_plan(&world.frame);
        let text = serde_json::to_string_pretty(&plan).unwrap();
        let back: QgcPlan = serde_json::from_str(&text).unwrap();
        assert_eq!(back, plan);
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(v["fileType"], "Plan");
        assert_eq!(v["version"], 1);
        assert_eq!(v["mission"]["version"], 2);
        let items = v["mission"]["items"].as_array().unwrap();
        assert_eq!(items[0]["command"], MAV_CMD_NAV_TAKEOFF);
        let waypoints = items.iter().filter(|i| i["command"] == MAV_CMD_NAV_WAYPOINT).count();
        let rois = items.iter().filter(|i| i["command"] == MAV_CMD_DO_SET_ROI_LOCATION).count();
        assert_eq!(waypoints, m.waypoints.len());
        assert_eq!(rois, waypoints);
        for item in items {
            assert_eq!(item["type"], "SimpleItem");
            assert_eq!(item["params"].as_array().unwrap().len(), 7);
        }
        // Waypoints are near the origin in WGS84.
        let wp = items.iter().find(|i| i["command"] == MAV_CMD_NAV_WAYPOINT).unwrap();
        let lat = wp["params"][4].as_f64().unwrap();
        assert!((lat - world.scenario.origin.lat_deg).abs() < 0.01);
    }

    #[test]
    fn indoor_flight_stays_over_the_floor_and_tilts_a_little() {
        let world = World::build(&Scenario::load("indoor-floor").unwrap()).unwrap();
        let m = Mission::plan(&world).unwrap();
        for k in 0..200 {
            let s = m.state(k as f64 * 0.5);
            assert!(s.position.x.abs() <= 4.0 && s.position.y.abs() <= 4.0);
            assert!(s.attitude[0].abs() < 0.2 && s.attitude[1].abs() < 0.2);
        }
    }

    #[test]
    fn resample_spacing() {
        let sq = vec![
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(10.0, 0.0, 0.0),
            Vec3::new(10.0, 10.0, 0.0),
            Vec3::new(0.0, 10.0, 0.0),
            Vec3::new(0.0, 0.0, 0.0),
        ];
        let pts = resample(&sq, 2.5);
        assert_eq!(pts.len(), 16);
    }
}
