//! The map refined after each landing (`area.attitude_prior_deg > 0`): the live area
//! pipeline keeps every sighting of the run and each frame's camera pose, and when the
//! autopilot says the vehicle has touched down it runs the bundle adjustment of
//! [`crate::area::refine`] over them (each frame's attitude, a static gimbal offset and the
//! landmarks together), as `mavloc area --trace` does on a recording after the flight.
//!
//! Why after the landing: the adjustment wants the whole flight (a static offset is told
//! apart from the frames' own errors only over hundreds of frames), and on a PX4 SITL
//! flight of 1861 frames it took 73 s of one core (session 34): too long to hold the
//! frames back, and while the vehicle stands the cores are free. In flight it runs only
//! when asked (`area.adjust_first_frames`, [`crate::daemon::live`]), at a lower priority
//! than the pipeline. Either way it runs on a thread of its own, beside the pipeline (which goes on with the frames the camera
//! still sends); its result becomes a new result set when it is done
//! ([`FlightLog::poll`]). A stop, or the log dropped (the pipeline reset or rebuilt, the
//! prior turned off), cancels it at its next round and leaves the filters' set, which was
//! complete before the adjustment began.
//!
//! The poses are kept as earth-frame angles in the configured gimbal chain, so the static
//! offset is an offset of those angles, as `gimbal.*_offset_deg` (what
//! [`crate::daemon::record`] writes for the offline run, with the offsets in force left
//! in). Frames posed by the fixed mount (no gimbal telemetry), which those offsets do not
//! touch, are left out.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use mavloc_data::dataset::{GimbalFrame, PoseRecord};
use mavloc_geometry::{CameraPose, GimbalChain};

use crate::align::AlignedPose;
use crate::area::refine::{self, RefineParams, Refined};
use crate::geometry::{Intrinsics, Pixel, Vec3};
use crate::output::LandmarkRecord;

/// Sightings kept at most, 16 bytes each (64 MB): a flight of 1861 frames had about 0.4
/// million. Beyond this the log stops growing and the adjustment runs on what it has,
/// saying so.
pub const MAX_SIGHTINGS: usize = 4_000_000;

/// Frames needed before an adjustment is worth running: a static offset and the frames'
/// own errors are told apart only over many frames.
pub const MIN_FRAMES: usize = 30;

/// One sighting, compact: frame and landmark numbers fit 32 bits for any flight the log
/// holds, and single precision keeps a pixel to a thousandth.
#[derive(Clone, Copy)]
struct Seen {
    frame: u32,
    id: u32,
    u: f32,
    v: f32,
}

/// Every sighting of the run, and each frame's pose, numbered by the pipeline's own count
/// of frames (a camera that reconnects numbers its frames from 0 again).
pub struct FlightLog {
    chain: GimbalChain,
    sightings: Vec<Seen>,
    poses: BTreeMap<u64, PoseRecord>,
    full: bool,
    running: Option<Running>,
}

struct Running {
    handle: std::thread::JoinHandle<Result<Refined, String>>,
    cancel: Arc<AtomicBool>,
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
#[derive(Debug)]
pub enum Poll {
    Idle,
    Running,
    Done(Box<Adjusted>),
    /// It could not run, or its thread panicked: why.
    Failed(String),
}

/// The camera pose of a logged frame with `offset` (yaw, pitch, roll, degrees) added to
/// its earth-frame angles: with no offset, the pose the pipeline had.
pub fn pose_at(r: &PoseRecord, chain: GimbalChain, offset: &Vec3) -> CameraPose {
    let g = r.gimbal_deg;
    let moved = PoseRecord { gimbal_deg: [g[0] + offset.x, g[1] + offset.y, g[2] + offset.z], ..*r };
    moved.camera_pose(chain, GimbalFrame::Earth)
}

impl FlightLog {
    pub fn new(chain: GimbalChain) -> FlightLog {
        FlightLog { chain, sightings: Vec::new(), poses: BTreeMap::new(), full: false, running: None }
    }

    pub fn frames(&self) -> usize {
        self.poses.len()
    }

    /// One processed frame: its pose and its sightings, landmark ids as the pipeline
    /// numbers them plus `id_offset` (as the results carry them). Returns true when this
    /// frame filled the log (it is then not in it).
    pub fn add(
        &mut self,
        frame: u64,
        pose: &AlignedPose,
        sightings: &[(u64, Pixel)],
        id_offset: u64,
    ) -> bool {
        if self.full || !pose.from_gimbal {
            return false;
        }
        let fits = |n: u64| u32::try_from(n).is_ok();
        if self.sightings.len() + sightings.len() > MAX_SIGHTINGS
            || !fits(frame)
            || sightings.iter().any(|(id, _)| !fits(id + id_offset))
        {
            self.full = true;
            return true;
        }
        self.sightings.extend(sightings.iter().map(|(id, px)| Seen {
            frame: frame as u32,
            id: (id + id_offset) as u32,
            u: px.u as f32,
            v: px.v as f32,
        }));
        self.poses.insert(frame, super::record::pose_record(pose, self.chain, [0.0; 3], |p| p));
        false
    }

    /// An adjustment has started and not been collected by [`FlightLog::poll`].
    pub fn running(&self) -> bool {
        self.running.is_some()
    }

    /// Starts the adjustment of `landmarks` (those seen at least twice in the log) on a
    /// thread of its own. `k`: the intrinsics the sightings are in; `prior_deg`: the SD of
    /// each frame's attitude; `bearing_noise_deg`: the filters' (a sighting is as good as
    /// that). Returns the frames it adjusts, or why it did not start.
    pub fn start(
        &mut self,
        landmarks: &[LandmarkRecord],
        k: &Intrinsics,
        prior_deg: f64,
        bearing_noise_deg: f64,
    ) -> Result<usize, String> {
        if self.running.is_some() {
            return Err("an adjustment is still running".into());
        }
        if self.poses.len() < MIN_FRAMES {
            return Err(format!("{} frames posed by the gimbal, fewer than {MIN_FRAMES}", self.poses.len()));
        }
        // Copies, so the log goes on growing while the thread works (16 bytes a sighting:
        // a few milliseconds for a long flight).
        let (seen, poses, landmarks) = (self.sightings.clone(), self.poses.clone(), landmarks.to_vec());
        let (chain, k) = (self.chain, *k);
        let cancel = Arc::new(AtomicBool::new(false));
        let params = RefineParams {
            pixel_sd: (bearing_noise_deg.to_radians() * k.fx).max(0.5),
            cancel: Some(cancel.clone()),
            ..RefineParams::new(prior_deg)
        };
        let frames = poses.len();
        let handle = std::thread::Builder::new()
            .name("mavloc-refine".into())
            .spawn(move || {
                yield_to_the_pipeline();
                let mut count: BTreeMap<u64, usize> = BTreeMap::new();
                for s in &seen {
                    *count.entry(s.id as u64).or_default() += 1;
                }
                let chosen: Vec<LandmarkRecord> =
                    landmarks.into_iter().filter(|l| count.get(&l.id).is_some_and(|n| *n >= 2)).collect();
                if chosen.is_empty() {
                    return Err("no converged landmark was seen twice in this run's frames".into());
                }
                let ids: std::collections::BTreeSet<u64> = chosen.iter().map(|l| l.id).collect();
                let sightings: Vec<(u64, u64, Pixel)> = seen
                    .iter()
                    .filter(|s| ids.contains(&(s.id as u64)))
                    .map(|s| (s.frame as u64, s.id as u64, Pixel::new(s.u as f64, s.v as f64)))
                    .collect();
                drop(seen);
                let frames: Vec<u64> = poses.keys().copied().collect();
                let pose = |f: u64, o: &Vec3| pose_at(&poses[&f], chain, o);
                Ok(refine::refine_with_offset(&sightings, &chosen, &frames, &pose, &k, &params))
            })
            .map_err(|e| format!("cannot start its thread: {e}"))?;
        self.running = Some(Running { handle, cancel, started: Instant::now(), frames });
        Ok(frames)
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
            Ok(Ok(refined)) => Poll::Done(Box::new(Adjusted { refined, frames: r.frames, elapsed_s })),
            Ok(Err(why)) => Poll::Failed(why),
            Err(p) => Poll::Failed(format!(
                "it panicked: {}",
                p.downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| p.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "unknown panic".into())
            )),
        }
    }
}

/// The nice value of the adjustment's thread: in flight (`area.adjust_first_frames`) it
/// shares the cores with the pipeline and the camera, which must keep their rate; the
/// adjustment takes what they leave.
const ADJUSTMENT_NICE: i32 = 10;

/// Lowers the calling thread's scheduling priority to [`ADJUSTMENT_NICE`]. On Linux the
/// nice value is per thread (setpriority(2) on a thread id); elsewhere nothing is done.
fn yield_to_the_pipeline() {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: the gettid system call and setpriority on this thread's own id touch no
        // memory. The system call, not glibc's gettid(), which glibc before 2.30 (Ubuntu
        // 18.04, JetPack 4) lacks.
        let done = unsafe {
            let tid = libc::syscall(libc::SYS_gettid);
            libc::setpriority(libc::PRIO_PROCESS, tid as libc::id_t, ADJUSTMENT_NICE)
        };
        if done != 0 {
            tracing::debug!(
                "area: the adjustment's thread keeps its priority: {}",
                std::io::Error::last_os_error()
            );
        }
    }
}

impl Drop for FlightLog {
    /// An adjustment nobody will collect is stopped at its next round, not left to use a
    /// core for minutes.
    fn drop(&mut self) {
        if let Some(r) = &self.running {
            r.cancel.store(true, Ordering::Relaxed);
            tracing::warn!("area: the map's adjustment after landing was abandoned (the pipeline stopped or was rebuilt)");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::align::VehicleSample;
    use mavloc_geometry::{GimbalAngles, Mount};
    use proptest::prelude::*;

    fn aligned(camera: CameraPose, from_gimbal: bool) -> AlignedPose {
        AlignedPose {
            autopilot_time: 0.0,
            vehicle: VehicleSample {
                position: camera.position,
                velocity: Vec3::zeros(),
                attitude: nalgebra::UnitQuaternion::from_euler_angles(0.1, -0.05, 1.0),
            },
            camera,
            from_gimbal,
        }
    }

    /// How far apart two rotations are (not `angle_to`, whose arccosine gives NaN for
    /// equal rotations a rounding away from the identity).
    fn apart(a: &crate::geometry::Rot3, b: &crate::geometry::Rot3) -> f64 {
        (a.matrix() - b.matrix()).norm()
    }

    proptest! {
        /// With no offset a logged frame is posed as the pipeline had it, whatever the
        /// chain and wherever the camera looks (straight down included); an offset turns
        /// it by that many degrees of the chain's angles.
        #[test]
        fn a_logged_pose_is_the_live_pose_and_an_offset_moves_its_angles(
            yaw in -180.0f64..180.0, pitch in -90.0f64..30.0, roll in -30.0f64..30.0,
            body in proptest::bool::ANY, ypr in proptest::bool::ANY,
            offset in proptest::array::uniform3(-3.0f64..3.0),
        ) {
            let chain = if ypr { GimbalChain::YawPitchRoll } else { GimbalChain::YawRollPitch };
            let mount = if body {
                Mount::Body { attitude: mavloc_geometry::body_rotation(0.2, -0.1, 0.7) }
            } else {
                Mount::Earth
            };
            let camera = CameraPose::from_gimbal(
                Vec3::new(10.0, -4.0, -50.0), chain, GimbalAngles::from_degrees(yaw, pitch, roll), mount,
            );
            let mut log = FlightLog::new(chain);
            log.add(7, &aligned(camera, true), &[], 0);
            let r = &log.poses[&7];
            let back = pose_at(r, chain, &Vec3::zeros());
            prop_assert!((back.position - camera.position).norm() < 1e-9);
            prop_assert!(apart(&back.attitude, &camera.attitude) < 1e-9, "{back:?} vs {camera:?}");
            let o = Vec3::from(offset);
            let moved = pose_at(r, chain, &o);
            let a = chain.angles(&camera.attitude);
            let want = chain.rotation(GimbalAngles::from_degrees(
                a.yaw.to_degrees() + o.x, a.pitch.to_degrees() + o.y, a.roll.to_degrees() + o.z,
            ));
            prop_assert!(apart(&moved.attitude, &want) < 1e-9);
        }
    }

    /// Frames the fixed mount posed are not logged (the gimbal offsets do not apply to
    /// them); a frame that would pass the cap fills the log and is left out whole.
    #[test]
    fn fixed_mount_frames_are_left_out_and_the_cap_keeps_whole_frames() {
        let camera = CameraPose::from_gimbal(
            Vec3::zeros(),
            GimbalChain::YawPitchRoll,
            GimbalAngles::from_degrees(0.0, -60.0, 0.0),
            Mount::Earth,
        );
        let mut log = FlightLog::new(GimbalChain::YawPitchRoll);
        let seen = [(1, Pixel::new(1.0, 2.0)), (2, Pixel::new(3.0, 4.0))];
        assert!(!log.add(0, &aligned(camera, false), &seen, 0));
        assert_eq!((log.frames(), log.sightings.len()), (0, 0));
        assert!(!log.add(1, &aligned(camera, true), &seen, 0));
        assert_eq!((log.frames(), log.sightings.len()), (1, 2));
        let many = vec![(3, Pixel::new(0.0, 0.0)); MAX_SIGHTINGS - 1];
        assert!(log.add(2, &aligned(camera, true), &many, 0), "full");
        assert_eq!((log.frames(), log.sightings.len()), (1, 2), "the frame that did not fit is not in it");
        assert!(!log.add(3, &aligned(camera, true), &seen, 0), "said once");
        assert_eq!(log.frames(), 1);
    }

    /// Too few frames: no adjustment, and why.
    #[test]
    fn an_adjustment_needs_frames() {
        let mut log = FlightLog::new(GimbalChain::YawPitchRoll);
        let k = Intrinsics::from_hfov(640, 480, 60f64.to_radians());
        let why = log.start(&[], &k, 1.0, 0.5).unwrap_err();
        assert!(why.contains("fewer than 30"), "{why}");
        assert!(matches!(log.poll(), Poll::Idle));
    }
}
