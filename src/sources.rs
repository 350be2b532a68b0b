//! Where frames come from in `flownav run`: a V4L2 camera (`--camera /dev/videoN`) or a frame
//! folder played as a camera (`--camera frames:DIR`).
//!
//! [`CameraSpec`] parses the `--camera` argument; [`open_camera`] turns it and the `[camera]`
//! config table into a [`SourceCamera`], one concrete type implementing [`hal::Camera`] for both,
//! so the runtime is written once. A [`FolderCamera`] plays its folder at the folder's own frame
//! rate (from `odometry.csv`, else the configured fps) and then reports
//! [`ErrorKind::EndOfStream`]: the runtime stops the robot and ends the run; or, looping
//! (`run --loop`), plays it again and again with ever-increasing stamps (soak tests).

use crate::frames::{FrameFolder, FramesError, load_luma};
use hal::camera::monotonic_ns;
use hal::v4l2::{CameraConfig, V4l2Camera, V4l2Error};
use hal::{Camera, Error, ErrorKind, Frame};
use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::Duration;

/// The `--camera` argument.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum CameraSpec {
    /// A V4L2 device node: `/dev/video0`, or a stable name such as `/dev/v4l/by-id/...`.
    Device(PathBuf),
    /// A frame folder played as a camera: `frames:DIR`.
    Frames(PathBuf),
}

/// A `--camera` value that is neither a device nor `frames:DIR`.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum CameraSpecError {
    #[error("--camera frames: needs a folder after the colon, e.g. frames:data/run1")]
    EmptyFolder,
    #[error("--camera {0}: that is a folder; to play it as a camera write frames:{0}")]
    FolderWithoutPrefix(String),
    #[error(
        "--camera {0}: expected a V4L2 device such as /dev/video0 (see `flownav devices`) or frames:DIR for a frame folder"
    )]
    Unrecognised(String),
}

impl FromStr for CameraSpec {
    type Err = CameraSpecError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        if let Some(dir) = s.strip_prefix("frames:") {
            return if dir.is_empty() { Err(CameraSpecError::EmptyFolder) } else { Ok(Self::Frames(dir.into())) };
        }
        if s.starts_with("/dev/") {
            return Ok(Self::Device(s.into()));
        }
        if Path::new(s).is_dir() {
            return Err(CameraSpecError::FolderWithoutPrefix(s.into()));
        }
        Err(CameraSpecError::Unrecognised(s.into()))
    }
}

impl fmt::Display for CameraSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            CameraSpec::Device(p) => write!(f, "{}", p.display()),
            CameraSpec::Frames(p) => write!(f, "frames:{}", p.display()),
        }
    }
}

impl CameraSpec {
    /// The camera the config file names when `--camera` is not given.
    pub fn from_config(cfg: &CameraConfig) -> Self {
        CameraSpec::Device(cfg.device.clone())
    }
}

/// Errors of a frame source; [`Error::kind`] says what the runtime does.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    #[error(transparent)]
    V4l2(#[from] V4l2Error),
    /// The folder cannot be played (missing, too few images, bad `odometry.csv`). Kind `Other`.
    #[error("--camera frames:{}: {source}", dir.display())]
    Folder { dir: PathBuf, source: FramesError },
    /// One image of the folder is unreadable; it is skipped. Kind `BadData`.
    #[error("frame {index} of the folder is unusable (skipped): {source}")]
    Frame { index: usize, path: PathBuf, source: FramesError },
    /// Kind `EndOfStream`.
    #[error("frame folder {} ended after {frames} frames", dir.display())]
    EndOfStream { dir: PathBuf, frames: usize },
    #[error("--camera frames:{}: playback rate {fps} fps is invalid: set camera.fps > 0 or add odometry.csv", dir.display())]
    BadFps { dir: PathBuf, fps: f64 },
}

impl Error for SourceError {
    fn kind(&self) -> ErrorKind {
        match self {
            SourceError::V4l2(e) => e.kind(),
            SourceError::Folder { .. } | SourceError::BadFps { .. } => ErrorKind::Other,
            SourceError::Frame { .. } => ErrorKind::BadData,
            SourceError::EndOfStream { .. } => ErrorKind::EndOfStream,
        }
    }
}

/// A frame folder played as a camera.
///
/// Frame `i` is due `t_i - t_0` seconds after the first capture, where `t_i` is its time in
/// `odometry.csv` or `i / fps` without one; its stamp is that due time on the monotonic clock
/// ([`monotonic_ns`]), so stamps are spaced exactly as recorded and compare with the base's
/// odometry stamps. `seq` is the frame's index in the folder (as in `flownav analyze`). After the
/// last frame every capture returns [`SourceError::EndOfStream`].
///
/// A looping camera ([`FolderCamera::looping`]) starts over after the last frame instead. Each
/// lap lasts the folder's span plus one mean frame interval, so the first frame of a lap comes
/// one interval after the last frame of the previous lap, as if the folder were recorded again
/// right after itself: stamps keep increasing (the pipeline refuses stamps that do not), and
/// `odometry.csv`'s times wrap with the frames. `seq` keeps counting across laps; the frame's
/// index in the folder is `seq % len()`.
#[derive(Debug)]
pub struct FolderCamera {
    folder: FrameFolder,
    /// Offset of each frame from the first, seconds.
    offsets_s: Vec<f64>,
    next: usize,
    /// Laps completed (looping only).
    lap: u64,
    start_ns: Option<u64>,
    /// How long the last frame took to load, ns (paced playback starts the next one that early).
    decode_ns: u64,
    paced: bool,
    looping: bool,
}

impl FolderCamera {
    /// Opens `dir`; `fps` is the playback rate used when the folder has no `odometry.csv`.
    pub fn open(dir: impl AsRef<Path>, fps: f64) -> Result<Self, SourceError> {
        let dir = dir.as_ref();
        let folder = FrameFolder::open(dir).map_err(|source| SourceError::Folder { dir: dir.into(), source })?;
        let offsets_s: Vec<f64> = match &folder.odometry {
            Some(rows) => rows.iter().map(|r| r.t - rows[0].t).collect(),
            None => {
                if !(fps.is_finite() && fps > 0.0) {
                    return Err(SourceError::BadFps { dir: dir.into(), fps });
                }
                (0..folder.images.len()).map(|i| i as f64 / fps).collect()
            }
        };
        Ok(Self { folder, offsets_s, next: 0, lap: 0, start_ns: None, decode_ns: 0, paced: true, looping: false })
    }

    /// Whether playback starts over after the last frame (default: it ends there).
    pub fn looping(mut self, looping: bool) -> Self {
        self.looping = looping;
        self
    }

    /// Length of one lap, s: the folder's span plus its mean frame interval.
    fn lap_s(&self) -> f64 {
        let span = self.offsets_s.last().copied().unwrap_or(0.0);
        span + span / (self.offsets_s.len().max(2) - 1) as f64
    }

    /// Whether `capture` waits until each frame is due (default) or returns at once with the
    /// same stamps (tests, and replaying faster than real time).
    pub fn paced(mut self, paced: bool) -> Self {
        self.paced = paced;
        self
    }

    /// The folder being played (its odometry, if any, is ground truth for the run).
    pub fn folder(&self) -> &FrameFolder {
        &self.folder
    }

    /// Number of frames in the folder.
    pub fn len(&self) -> usize {
        self.folder.images.len()
    }

    /// Always false: a playable folder holds at least two frames.
    pub fn is_empty(&self) -> bool {
        self.folder.images.is_empty()
    }
}

impl Camera for FolderCamera {
    type Error = SourceError;

    fn capture(&mut self) -> Result<Frame, SourceError> {
        if self.looping && self.next == self.len() {
            self.next = 0;
            self.lap += 1;
        }
        let index = self.next;
        let Some(path) = self.folder.images.get(index).cloned() else {
            return Err(SourceError::EndOfStream { dir: self.folder.dir.clone(), frames: self.len() });
        };
        self.next += 1;
        let start = *self.start_ns.get_or_insert_with(monotonic_ns);
        // Whole laps and the offset in the lap are rounded separately, so a lap adds the same
        // number of nanoseconds every time, however long the run.
        let lap_ns = (self.lap_s() * 1e9).round() as u64;
        let t_ns = start + self.lap * lap_ns + (self.offsets_s[index] * 1e9).round() as u64;
        let seq = self.lap * self.len() as u64 + index as u64;
        if self.paced {
            // Decode just before the frame is due, as a camera's frame arrives then, instead of
            // right after the previous one, while the step of that one wants the cores.
            let lead = self.decode_ns.saturating_mul(3) / 2 + 1_000_000;
            let now = monotonic_ns();
            if t_ns.saturating_sub(lead) > now {
                std::thread::sleep(Duration::from_nanos(t_ns - lead - now));
            }
        }
        let started = monotonic_ns();
        let image = load_luma(&path).map_err(|source| SourceError::Frame { index, path: path.clone(), source })?;
        self.decode_ns = monotonic_ns().saturating_sub(started);
        if self.paced {
            let now = monotonic_ns();
            if t_ns > now {
                std::thread::sleep(Duration::from_nanos(t_ns - now));
            }
        }
        Ok(Frame { seq, t_ns, image })
    }
}

/// A camera of either kind, so the runtime needs one code path.
pub enum SourceCamera {
    V4l2(Box<V4l2Camera>),
    Folder(FolderCamera),
}

impl Camera for SourceCamera {
    type Error = SourceError;

    fn capture(&mut self) -> Result<Frame, SourceError> {
        match self {
            SourceCamera::V4l2(c) => Ok(c.capture()?),
            SourceCamera::Folder(c) => c.capture(),
        }
    }

    fn take_encoded(&mut self) -> Option<std::sync::Arc<[u8]>> {
        match self {
            SourceCamera::V4l2(c) => c.take_encoded(),
            SourceCamera::Folder(_) => None,
        }
    }
}

/// Opens the camera `spec` names: a device is negotiated with `cfg`'s format, size, fps and stall
/// timeout (`cfg.device` is replaced by the spec's path); a folder plays at its `odometry.csv`
/// times, else at `cfg.fps`, once or (`looping`) over and over.
pub fn open_camera(spec: &CameraSpec, cfg: &CameraConfig, looping: bool) -> Result<SourceCamera, SourceError> {
    match spec {
        CameraSpec::Device(path) => {
            let cfg = CameraConfig { device: path.clone(), ..cfg.clone() };
            Ok(SourceCamera::V4l2(Box::new(V4l2Camera::open(&cfg)?)))
        }
        CameraSpec::Frames(dir) => Ok(SourceCamera::Folder(FolderCamera::open(dir, cfg.fps)?.looping(looping))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frames::save_png;
    use hal::LumaImage;

    fn folder(n: usize, odometry: Option<&str>) -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        for i in 0..n {
            save_png(&LumaImage::from_fn(8, 6, |x, y| (i * 10 + x + y) as u8), dir.path().join(format!("{i:04}.png")))
                .unwrap();
        }
        if let Some(csv) = odometry {
            std::fs::write(dir.path().join("odometry.csv"), csv).unwrap();
        }
        dir
    }

    #[test]
    fn specs_parse_with_clear_errors() {
        assert_eq!("/dev/video2".parse(), Ok(CameraSpec::Device("/dev/video2".into())));
        assert_eq!("frames:data/run".parse(), Ok(CameraSpec::Frames("data/run".into())));
        assert_eq!("frames:".parse::<CameraSpec>(), Err(CameraSpecError::EmptyFolder));
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path().to_str().unwrap();
        let e = d.parse::<CameraSpec>().unwrap_err();
        assert!(e.to_string().contains(&format!("frames:{d}")), "{e}");
        let e = "video0".parse::<CameraSpec>().unwrap_err();
        assert!(e.to_string().contains("/dev/video0") && e.to_string().contains("frames:DIR"), "{e}");
        assert_eq!(CameraSpec::Frames("x".into()).to_string(), "frames:x");
    }

    #[test]
    fn plays_frames_in_order_with_recorded_spacing_then_ends() {
        let dir = folder(3, Some("t,v,omega\n10.0,0.2,0\n10.05,0.2,0\n10.25,0.2,0\n"));
        let mut cam = FolderCamera::open(dir.path(), 30.0).unwrap().paced(false);
        let frames: Vec<Frame> = (0..3).map(|_| cam.capture().unwrap()).collect();
        assert_eq!(frames.iter().map(|f| f.seq).collect::<Vec<_>>(), [0, 1, 2]);
        let dt: Vec<u64> = frames.iter().map(|f| f.t_ns - frames[0].t_ns).collect();
        assert_eq!(dt, [0, 50_000_000, 250_000_000]);
        assert_eq!(frames[2].image.get(0, 0), 20, "third file's pixels");
        for _ in 0..2 {
            let e = cam.capture().unwrap_err();
            assert_eq!(e.kind(), ErrorKind::EndOfStream, "{e}");
        }
    }

    #[test]
    fn a_looping_folder_repeats_its_frames_with_increasing_stamps() {
        // Frames 50 ms and 200 ms apart: span 0.25 s, mean interval 0.125 s, lap 0.375 s.
        let dir = folder(3, Some("t,v,omega\n10.0,0.2,0\n10.05,0.2,0\n10.25,0.2,0\n"));
        let mut cam = FolderCamera::open(dir.path(), 30.0).unwrap().paced(false).looping(true);
        let frames: Vec<Frame> = (0..8).map(|_| cam.capture().unwrap()).collect();
        assert_eq!(frames.iter().map(|f| f.seq).collect::<Vec<_>>(), [0, 1, 2, 3, 4, 5, 6, 7]);
        let pixels: Vec<u8> = frames.iter().map(|f| f.image.get(0, 0)).collect();
        assert_eq!(pixels, [0, 10, 20, 0, 10, 20, 0, 10], "the folder's frames, in order, lap after lap");
        let dt_ms: Vec<u64> = frames.iter().map(|f| (f.t_ns - frames[0].t_ns) / 1_000_000).collect();
        assert_eq!(dt_ms, [0, 50, 250, 375, 425, 625, 750, 800]);
        // A folder without odometry.csv loops at its fps.
        let dir = folder(2, None);
        let mut cam = FolderCamera::open(dir.path(), 10.0).unwrap().paced(false).looping(true);
        let t: Vec<u64> = (0..5).map(|_| cam.capture().unwrap().t_ns).collect();
        assert!(t.windows(2).all(|w| w[1] - w[0] == 100_000_000), "{t:?}");
    }

    #[test]
    fn paced_playback_is_never_early() {
        let dir = folder(2, None);
        let mut cam = FolderCamera::open(dir.path(), 50.0).unwrap();
        let a = cam.capture().unwrap();
        let b = cam.capture().unwrap();
        assert_eq!(b.t_ns - a.t_ns, 20_000_000);
        assert!(monotonic_ns() >= b.t_ns, "frame 1 was delivered before it was due");
    }

    #[test]
    fn missing_folder_and_corrupt_frame_are_named() {
        let e = FolderCamera::open("/nonexistent/flownav-frames", 30.0).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Other);
        assert!(e.to_string().contains("/nonexistent/flownav-frames"), "{e}");

        let dir = folder(3, None);
        std::fs::write(dir.path().join("0001.png"), b"not a png").unwrap();
        let mut cam = FolderCamera::open(dir.path(), 30.0).unwrap().paced(false);
        assert_eq!(cam.capture().unwrap().seq, 0);
        let e = cam.capture().unwrap_err();
        assert_eq!(e.kind(), ErrorKind::BadData);
        assert!(e.to_string().contains("0001.png"), "{e}");
        assert_eq!(cam.capture().unwrap().seq, 2, "playback goes on after a corrupt frame");
        assert_eq!(cam.capture().unwrap_err().kind(), ErrorKind::EndOfStream);

        let e = FolderCamera::open(dir.path(), 0.0).unwrap_err();
        assert!(e.to_string().contains("camera.fps"), "{e}");
    }

    #[test]
    fn open_camera_dispatches_on_the_spec() {
        let dir = folder(2, None);
        let cfg = CameraConfig::default();
        let mut cam = open_camera(&CameraSpec::Frames(dir.path().into()), &cfg, false).unwrap();
        assert!(matches!(cam, SourceCamera::Folder(_)));
        assert_eq!(cam.capture().unwrap().seq, 0);
        let e = open_camera(&CameraSpec::Device("/dev/video_flownav_absent".into()), &cfg, false).err().unwrap();
        assert_eq!(e.kind(), ErrorKind::Disconnected);
        assert!(e.to_string().contains("/dev/video_flownav_absent"), "{e}");
    }
}
