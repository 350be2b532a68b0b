//! Reading images and frame folders from disk (the DESIGN.md frame-folder format).
//!
//! A frame folder holds PNG or JPEG images read in lexical file-name order and, optionally,
//! `odometry.csv` with header `t,v,omega` (s, m/s, rad/s), one row per frame.

use hal::LumaImage;
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum FramesError {
    #[error("cannot read image {path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("{path} is empty (0 bytes): expected a PNG or JPEG image")]
    Empty { path: PathBuf },
    #[error("{path} is not a readable PNG/JPEG image: {message}")]
    Decode { path: PathBuf, message: String },
    #[error("cannot list frame folder {path}: {source} (pass an existing folder of PNG/JPEG frames)")]
    Folder { path: PathBuf, source: std::io::Error },
    #[error("frame folder {path} holds {count} image(s); at least 2 are needed for flow")]
    TooFewFrames { path: PathBuf, count: usize },
    #[error("{path}: line {line}: {message} (expected header `t,v,omega` and one row per frame: seconds, m/s, rad/s)")]
    Odometry { path: PathBuf, line: usize, message: String },
}

/// Loads an image file as 8-bit luma; colour is converted with Rec.601 weights (as OpenCV's
/// BGR2GRAY and the `image` crate do).
pub fn load_luma(path: impl AsRef<Path>) -> Result<LumaImage, FramesError> {
    let path = path.as_ref();
    let bytes = std::fs::read(path).map_err(|source| FramesError::Read { path: path.into(), source })?;
    decode_luma(&bytes, path)
}

/// Decodes PNG/JPEG bytes to luma; `path` only names the source in errors.
pub fn decode_luma(bytes: &[u8], path: &Path) -> Result<LumaImage, FramesError> {
    if bytes.is_empty() {
        return Err(FramesError::Empty { path: path.into() });
    }
    let img = image::load_from_memory(bytes)
        .map_err(|e| FramesError::Decode { path: path.into(), message: e.to_string() })?;
    let gray = img.into_luma8();
    let (w, h) = gray.dimensions();
    Ok(LumaImage::from_vec(w as usize, h as usize, gray.into_raw()).expect("image crate returns w*h luma bytes"))
}

/// Saves a luma image as PNG.
pub fn save_png(img: &LumaImage, path: impl AsRef<Path>) -> Result<(), image::ImageError> {
    image::save_buffer(path, img.data(), img.width() as u32, img.height() as u32, image::ExtendedColorType::L8)
}

/// The reference data with ground truth that ships in the repository's `data/` folder (see its
/// README): real image pairs for the flow accuracy tests and benchmarks, and the scikit-fuzzy
/// grid. `FLOWNAV_DATA` overrides the location.
pub fn reference_data_dir() -> PathBuf {
    std::env::var_os("FLOWNAV_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("data"))
}

/// One row of `odometry.csv`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OdometryRow {
    pub t: f64,
    pub v: f64,
    pub omega: f64,
}

/// A frame folder: its image paths in lexical order and its odometry, if any.
#[derive(Clone, Debug)]
pub struct FrameFolder {
    pub dir: PathBuf,
    pub images: Vec<PathBuf>,
    pub odometry: Option<Vec<OdometryRow>>,
}

impl FrameFolder {
    /// Lists `dir`; reads and checks `odometry.csv` when present.
    pub fn open(dir: impl AsRef<Path>) -> Result<Self, FramesError> {
        let dir = dir.as_ref().to_path_buf();
        let entries = std::fs::read_dir(&dir).map_err(|source| FramesError::Folder { path: dir.clone(), source })?;
        let mut images: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_file())
            .filter(|p| {
                p.extension()
                    .and_then(|e| e.to_str())
                    .is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg"))
            })
            .collect();
        images.sort();
        if images.len() < 2 {
            return Err(FramesError::TooFewFrames { path: dir, count: images.len() });
        }
        let odo_path = dir.join("odometry.csv");
        let odometry = if odo_path.exists() { Some(read_odometry(&odo_path, images.len())?) } else { None };
        Ok(Self { dir, images, odometry })
    }

    /// Time and body velocity of frame `i`: from `odometry.csv`, else from the constant
    /// `velocity` (m/s) and `fps`.
    pub fn motion(&self, i: usize, velocity: f64, fps: f64) -> OdometryRow {
        match &self.odometry {
            Some(rows) => rows[i],
            None => OdometryRow { t: i as f64 / fps, v: velocity, omega: 0.0 },
        }
    }
}

fn read_odometry(path: &Path, frames: usize) -> Result<Vec<OdometryRow>, FramesError> {
    let err = |line: usize, message: String| FramesError::Odometry { path: path.into(), line, message };
    let text = std::fs::read_to_string(path).map_err(|source| FramesError::Read { path: path.into(), source })?;
    let mut lines = text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty());
    match lines.next() {
        Some((_, header)) if header.split(',').map(str::trim).eq(["t", "v", "omega"]) => {}
        Some((i, header)) => return Err(err(i + 1, format!("header is `{header}`"))),
        None => return Err(err(1, "file is empty".into())),
    }
    let mut rows = Vec::new();
    for (i, line) in lines {
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        if fields.len() != 3 {
            return Err(err(i + 1, format!("{} fields, expected 3", fields.len())));
        }
        let mut nums = [0.0; 3];
        for (n, f) in nums.iter_mut().zip(&fields) {
            *n = f
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| err(i + 1, format!("`{f}` is not a number")))?;
        }
        if let Some(prev) = rows.last().map(|r: &OdometryRow| r.t)
            && nums[0] <= prev
        {
            return Err(err(i + 1, format!("time {} does not increase", nums[0])));
        }
        rows.push(OdometryRow { t: nums[0], v: nums[1], omega: nums[2] });
    }
    if rows.len() != frames {
        return Err(err(0, format!("{} rows for {} frames", rows.len(), frames)));
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn empty_and_garbage_files_give_named_errors() {
        let dir = tempfile::tempdir().unwrap();
        let empty = dir.path().join("empty.png");
        std::fs::write(&empty, b"").unwrap();
        assert!(matches!(load_luma(&empty), Err(FramesError::Empty { .. })));
        let junk = dir.path().join("junk.png");
        std::fs::write(&junk, b"this is not an image").unwrap();
        let e = load_luma(&junk).unwrap_err();
        assert!(e.to_string().contains("junk.png"), "{e}");
        assert!(matches!(load_luma(dir.path().join("missing.png")), Err(FramesError::Read { .. })));
    }

    #[test]
    fn colour_is_converted_on_load() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("rgb.png");
        image::save_buffer(&p, &[255, 0, 0, 0, 255, 0], 2, 1, image::ExtendedColorType::Rgb8).unwrap();
        let img = load_luma(&p).unwrap();
        assert_eq!((img.width(), img.height()), (2, 1));
        assert!(img.get(1, 0) > img.get(0, 0), "green is brighter than red in luma");
    }

    #[test]
    fn odometry_is_checked() {
        let dir = tempfile::tempdir().unwrap();
        for i in 0..3 {
            save_png(&LumaImage::new(4, 4), dir.path().join(format!("{i:04}.png"))).unwrap();
        }
        std::fs::write(dir.path().join("odometry.csv"), "t,v,omega\n0,0.2,0\n0.1,0.2,0\n0.2,0.2,0.1\n").unwrap();
        let f = FrameFolder::open(dir.path()).unwrap();
        assert_eq!(f.images.len(), 3);
        assert_eq!(f.motion(2, 0.0, 10.0), OdometryRow { t: 0.2, v: 0.2, omega: 0.1 });
        std::fs::write(dir.path().join("odometry.csv"), "t,v,omega\n0,0.2,0\n0.1,x,0\n0.2,0.2,0.1\n").unwrap();
        let e = FrameFolder::open(dir.path()).unwrap_err();
        assert!(e.to_string().contains("line 3"), "{e}");
    }
}
