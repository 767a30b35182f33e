//! The map refined after each landing (`area.attitude_prior_deg > 0`): the live area
//! pipeline keeps every sighting of the run and each frame's camera pose, and when the
//! autopilot says the vehicle has touched down it runs the bundle adjustment of
//! [`crate::area::refine`] over them (each frame's attitude, a static gimbal offset and the
//! landmarks together), as `mavloc area --trace` does on a recording after the flight.
//!
//! Why after the landing and not in the air: the adjustment wants the whole flight (a
//! static offset is told apart from the frames' own errors only over hundreds of frames),
//! and on a recorded PX4 SITL flight of 1874 frames it took about 70 s of one core
//! (session 33): too long to hold the frames back, and while the vehicle stands the
//! cores are free. So it runs on a thread of its own, beside the pipeline (which goes on
//! with the frames the camera still sends); its result becomes a new result set when it
//! is done ([`FlightLog::poll`]). A stop before then leaves the filters' set, which was
//! complete before the adjustment began.
//!
//! The poses are kept as earth-frame angles in the configured gimbal chain, so the static
//! offset is an offset of those angles, as `gimbal.*_offset_deg` (what
//! [`crate::daemon::record`] writes for the offline run, with the offsets in force left in).

use std::collections::BTreeMap;
use std::time::Instant;

use mavloc_data::dataset::{GimbalFrame, PoseRecord};
use mavloc_geometry::GimbalChain;

use crate::align::AlignedPose;
use crate::area::refine::{self, RefineParams, Refined};
use crate::geometry::{Intrinsics, Pixel, Vec3};
use crate::output::LandmarkRecord;

/// Sightings kept at most (about 32 bytes each): a flight of 1874 frames had 0.4 million
/// (session 32's recording). Beyond this the log stops growing and the adjustment runs on
/// what it has, saying so.
pub const MAX_SIGHTINGS: usize = 20_000_000;

/// Frames needed before an adjustment is worth running: a static offset and the frames'
/// own errors are told apart only over many frames.
pub const MIN_FRAMES: usize = 30;

/// Every sighting of the run, and each frame's pose, numbered by the pipeline's own count
/// of frames (a camera that reconnects numbers its frames from 0 again).
pub struct FlightLog {
    chain: GimbalChain,
    sightings: Vec<(u64, u64, Pixel)>,
    poses: BTreeMap<u64, PoseRecord>,
    full: bool,
    running: Option<Running>,
}

struct Running {
    handle: std::thread::JoinHandle<Refined>,
    started: Instant,
    frames: usize,
}

/// A finished adjustment, for the results.
#[derive(Clone, Debug)]
pub struct Adjusted {
    pub refined: Refined,
    pub frames: usize,
    pub elapsed_s: f64,
}

/// What [`FlightLog::poll`] found.
pub enum Poll {
    Idle,
    Running,
    Done(Adjusted),
    /// The adjustment's thread panicked.
    Failed(String),
}

impl FlightLog {
    pub fn new(chain: GimbalChain) -> FlightLog {
        FlightLog { chain, sightings: Vec::new(), poses: BTreeMap::new(), full: false, running: None }
    }

    pub fn frames(&self) -> usize {
        self.poses.len()
    }

    /// One processed frame: its pose and its sightings (landmark ids as the results carry
    /// them). Returns true the first time the log is full.
    pub fn add(
        &mut self,
        frame: u64,
        pose: &AlignedPose,
        sightings: impl Iterator<Item = (u64, Pixel)>,
    ) -> bool {
        if self.full {
            return false;
        }
        let at = self.sightings.len();
        self.sightings.extend(sightings.map(|(id, px)| (frame, id, px)));
        if self.sightings.len() > MAX_SIGHTINGS {
            self.sightings.truncate(at);
            self.full = true;
            return true;
        }
        self.poses.insert(frame, super::record::pose_record(pose, self.chain, [0.0; 3], |p| p));
        false
    }

    /// An adjustment has started and not been collected by [`FlightLog::poll`].
    pub fn running(&self) -> bool {
        self.running.is_some()
    }

    pub fn full(&self) -> bool {
        self.full
    }

    /// Starts the adjustment of `landmarks` (those seen at least twice in the log) on a
    /// thread of its own. `k`: the intrinsics the sightings are in; `prior_deg`: the SD of
    /// each frame's attitude; `bearing_noise_deg`: the filters' (a sighting is as good as
    /// that). Returns why it did not start, if it did not.
    pub fn start(
        &mut self,
        landmarks: &[LandmarkRecord],
        k: &Intrinsics,
        prior_deg: f64,
        bearing_noise_deg: f64,
    ) -> Result<(usize, usize), String> {
        if self.running.is_some() {
            return Err("an adjustment is still running".into());
        }
        if self.poses.len() < MIN_FRAMES {
            return Err(format!("{} frames, fewer than {MIN_FRAMES}", self.poses.len()));
        }
        let mut seen: BTreeMap<u64, usize> = BTreeMap::new();
        for (_, id, _) in &self.sightings {
            *seen.entry(*id).or_default() += 1;
        }
        let chosen: Vec<LandmarkRecord> =
            landmarks.iter().filter(|l| seen.get(&l.id).is_some_and(|n| *n >= 2)).cloned().collect();
        if chosen.is_empty() {
            return Err("no converged landmark was seen twice in this run's frames".into());
        }
        let ids: std::collections::BTreeSet<u64> = chosen.iter().map(|l| l.id).collect();
        let sightings: Vec<_> =
            self.sightings.iter().filter(|(_, id, _)| ids.contains(id)).copied().collect();
        let poses = self.poses.clone();
        let (chain, k) = (self.chain, *k);
        let params = RefineParams {
            pixel_sd: (bearing_noise_deg.to_radians() * k.fx).max(0.5),
            ..RefineParams::new(prior_deg)
        };
        let n = (poses.len(), chosen.len());
        let handle = std::thread::Builder::new()
            .name("mavloc-refine".into())
            .spawn(move || {
                let frames: Vec<u64> = poses.keys().copied().collect();
                let pose = |f: u64, o: &Vec3| {
                    let r = &poses[&f];
                    let g = r.gimbal_deg;
                    let moved = PoseRecord { gimbal_deg: [g[0] + o.x, g[1] + o.y, g[2] + o.z], ..*r };
                    moved.camera_pose(chain, GimbalFrame::Earth)
                };
                refine::refine_with_offset(&sightings, &chosen, &frames, &pose, &k, &params)
            })
            .map_err(|e| format!("cannot start its thread: {e}"))?;
        self.running = Some(Running { handle, started: Instant::now(), frames: n.0 });
        Ok(n)
    }

    /// Whether an adjustment has finished, without waiting for it.
    pub fn poll(&mut self) -> Poll {
        match &self.running {
            None => return Poll::Idle,
            Some(r) if !r.handle.is_finished() => return Poll::Running,
            Some(_) => {}
        }
        let r = self.running.take().expect("checked");
        let elapsed_s = r.started.elapsed().as_secs_f64();
        match r.handle.join() {
            Ok(refined) => Poll::Done(Adjusted { refined, frames: r.frames, elapsed_s }),
            Err(p) => Poll::Failed(
                p.downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| p.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "unknown panic".into()),
            ),
        }
    }

    /// Waits for a running adjustment.
    pub fn wait(&mut self) -> Poll {
        loop {
            match self.poll() {
                Poll::Running => std::thread::sleep(std::time::Duration::from_millis(20)),
                other => return other,
            }
        }
    }
}
