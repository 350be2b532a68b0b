//! MCAP logging end to end: what is written reads back identical, split logs stay
//! self-contained, and a writer killed with SIGKILL leaves its flushed chunks readable.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use flownav::logging::sample::{self, SampleImages};
use flownav::logging::{LogEvent, LogInfo, LogOptions, LogReader, LogWriter, LoggedImage, encode};

fn read_all(paths: &[PathBuf]) -> (Vec<flownav::logging::LogEntry>, LogReader) {
    let mut reader = LogReader::open_parts(paths.to_vec()).unwrap();
    let entries: Vec<_> = reader.by_ref().collect::<Result<_, _>>().unwrap();
    (entries, reader)
}

#[test]
fn a_sim_log_reads_back_exactly_in_time_order() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sim.mcap");
    let frames = 40;
    let summary = sample::write_sample(&path, frames, SampleImages::Mono8, LogOptions::new("sim")).unwrap();
    assert_eq!(summary.files, vec![path.clone()]);
    assert_eq!(summary.stats.dropped(), 0, "{:?}", summary.stats);
    assert_eq!(summary.per_topic["/camera/image"], frames);
    assert_eq!(summary.per_topic["/control/setpoint"], frames - 1);

    let (entries, reader) = read_all(std::slice::from_ref(&path));
    assert!(reader.truncated().is_empty());
    assert!(entries.windows(2).all(|w| w[0].log_time_ns <= w[1].log_time_ns), "not in log-time order");
    let frames_back: Vec<_> = entries
        .iter()
        .filter_map(|e| match &e.event {
            LogEvent::Image(LoggedImage::Mono8(img)) => Some((e.t_ns, img.clone())),
            _ => None,
        })
        .collect();
    assert_eq!(frames_back.len() as u64, frames);
    for (i, (t, img)) in frames_back.iter().enumerate() {
        assert_eq!(*t, i as u64 * sample::FRAME_NS);
        assert_eq!(*img, sample::frame(i as u64, 320, 240), "frame {i} differs");
    }
    let odometry: Vec<_> =
        entries.iter().filter_map(|e| if let LogEvent::Odometry(o) = e.event { Some(o) } else { None }).collect();
    assert_eq!(odometry, (0..2 * frames).map(sample::odometry).collect::<Vec<_>>());
    // Bit-exact comparison the way replay --check does it: encode the recomputed value, compare bytes.
    let mut setpoints = 0;
    for e in &entries {
        if let LogEvent::Setpoint(s) = &e.event {
            let i = e.t_ns / sample::FRAME_NS;
            assert_eq!(*s, sample::setpoint(i));
            assert_eq!(e.data, encode::setpoint(&sample::setpoint(i)));
            setpoints += 1;
        }
        if let LogEvent::Perception(p) = &e.event {
            let i = e.t_ns / sample::FRAME_NS;
            assert_eq!(p.perception, sample::perception(i));
            assert_eq!(e.data, encode::perception(&sample::perception(i), &p.attributes));
        }
    }
    assert_eq!(setpoints, frames - 1);
    assert!(entries.iter().any(|e| matches!(&e.event, LogEvent::Calibration(c) if c.camera.width == 320)));
    assert!(entries.iter().any(|e| e.topic == "/sim/world"));

    let info = LogInfo::read(&path).unwrap();
    assert!(info.complete && info.truncation.is_none());
    assert!(info.stats_final && info.stats.as_ref().unwrap().dropped() == 0);
    let topic = |name: &str| info.topics.iter().find(|t| t.topic == name).unwrap();
    assert_eq!(topic("/camera/image").schema, "foxglove.RawImage");
    assert_eq!(topic("/camera/image").count, frames);
    assert_eq!(topic("/base/odometry").count, 2 * frames);
    assert_eq!(topic("/flow/annotations").count, frames - 1);
    assert!(info.topics.iter().all(|t| t.out_of_order == 0 && t.sequence_regressions == 0));
    assert!((info.duration_s() - (2 * frames - 1) as f64 * sample::FRAME_NS as f64 / 2e9).abs() < 1e-3);
    assert!(info.render().contains("complete"));
}

#[test]
fn jpeg_frames_are_stored_without_re_encoding() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.mcap");
    sample::write_sample(&path, 5, SampleImages::Jpeg, LogOptions::new("run")).unwrap();
    let (entries, _) = read_all(&[path]);
    let jpegs: Vec<_> = entries
        .iter()
        .filter_map(|e| if let LogEvent::Image(LoggedImage::Jpeg(b)) = &e.event { Some(b.clone()) } else { None })
        .collect();
    assert_eq!(jpegs.len(), 5);
    for (i, bytes) in jpegs.iter().enumerate() {
        assert_eq!(*bytes, sample::jpeg_frame(i as u64, 320, 240));
    }
}

#[test]
fn split_parts_are_complete_files_that_read_back_as_one_log() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("split.mcap");
    let mut options = LogOptions::new("sim").split_mb(0.2);
    options.chunk_bytes = 64 * 1024;
    let summary = sample::write_sample(&path, 30, SampleImages::Mono8, options).unwrap();
    assert!(summary.files.len() >= 3, "{:?}", summary.files);
    assert_eq!(summary.files[1], dir.path().join("split-p002.mcap"));
    for f in &summary.files {
        let info = LogInfo::read(f).unwrap();
        assert!(info.complete, "{} incomplete", f.display());
        let calib = info.topics.iter().find(|t| t.topic == "/camera/calibration").map_or(0, |t| t.count);
        assert_eq!(calib, 1, "{} lacks the calibration", f.display());
    }
    let (entries, _) = read_all(&summary.files);
    let images = entries.iter().filter(|e| matches!(e.event, LogEvent::Image(_))).count();
    assert_eq!(images, 30);
}

#[test]
fn an_existing_file_is_never_overwritten_and_default_names_are_unique() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("x.mcap");
    std::fs::write(&path, b"keep").unwrap();
    let err = LogWriter::create_at(&path, LogOptions::new("sim")).err().unwrap();
    assert!(err.to_string().contains("already exists"), "{err}");
    assert_eq!(std::fs::read(&path).unwrap(), b"keep");
    let a = LogWriter::create(dir.path(), LogOptions::new("sim")).unwrap();
    let b = LogWriter::create(dir.path(), LogOptions::new("sim")).unwrap();
    assert_ne!(a.path(), b.path());
    let name = a.path().file_name().unwrap().to_string_lossy().into_owned();
    assert!(name.starts_with("flownav-") && name.ends_with("-sim.mcap"), "{name}");
    a.close().unwrap();
    b.close().unwrap();
}

#[test]
fn every_prefix_of_a_log_is_readable_up_to_its_last_whole_chunk() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("full.mcap");
    let mut options = LogOptions::new("sim");
    options.chunk_bytes = 32 * 1024;
    sample::write_sample(&path, 20, SampleImages::Mono8, options).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let total = LogInfo::read(&path).unwrap().messages;
    let mut previous = 0;
    for cut in (64..bytes.len()).step_by(bytes.len() / 37) {
        let cut_path = dir.path().join(format!("cut-{cut}.mcap"));
        std::fs::write(&cut_path, &bytes[..cut]).unwrap();
        let info = LogInfo::read(&cut_path).unwrap();
        assert!(!info.complete && info.truncation.is_some());
        assert!(info.render().contains("truncated: no summary"));
        assert!(info.messages >= previous && info.messages <= total, "cut {cut}: {} messages", info.messages);
        previous = info.messages;
    }
    assert!(previous > total / 2, "late cuts recovered only {previous} of {total}");
}

const CHILD_ENV: &str = "FLOWNAV_LOG_CRASH_CHILD";
const FLUSHED_SETPOINTS: u64 = 200;

/// Not a test on its own: the writer process of `a_killed_writer_leaves_its_flushed_chunks_readable`
/// (the test binary re-executes itself with `CHILD_ENV` set).
#[test]
fn crash_child_helper() {
    let Ok(path) = std::env::var(CHILD_ENV) else { return };
    let path = PathBuf::from(path);
    let mut options = LogOptions::new("sim");
    options.flush_interval = Duration::from_millis(20);
    let writer = LogWriter::create_at(&path, options).unwrap();
    for i in 0..FLUSHED_SETPOINTS {
        writer.setpoint(i * sample::FRAME_NS, &sample::setpoint(i));
        writer.odometry(&sample::odometry(i));
    }
    // Wait until the file itself shows every set-point: the chunks are on disk.
    loop {
        let flushed = LogInfo::read(&path)
            .ok()
            .and_then(|info| info.topics.iter().find(|t| t.topic == "/control/setpoint").map(|t| t.count))
            .unwrap_or(0);
        if flushed >= FLUSHED_SETPOINTS {
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    println!("FLUSHED");
    // Keep writing (an open chunk at the moment of the kill) until killed.
    let mut i = FLUSHED_SETPOINTS;
    loop {
        writer.image_mono8(i * sample::FRAME_NS, &sample::frame(i, 64, 48));
        writer.setpoint(i * sample::FRAME_NS, &sample::setpoint(i));
        i += 1;
        std::thread::sleep(Duration::from_millis(1));
    }
}

fn spawn_writer(path: &Path) -> std::process::Child {
    Command::new(std::env::current_exe().unwrap())
        .args(["--exact", "crash_child_helper", "--nocapture", "--test-threads=1"])
        .env(CHILD_ENV, path)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

#[test]
fn a_killed_writer_leaves_its_flushed_chunks_readable() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("killed.mcap");
    let mut child = spawn_writer(&path);
    let mut stdout = BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    while !line.contains("FLUSHED") {
        line.clear();
        assert!(stdout.read_line(&mut line).unwrap() > 0, "the writer process ended before flushing");
    }
    child.kill().unwrap(); // SIGKILL: no destructor, no footer
    child.wait().unwrap();

    let info = LogInfo::read(&path).unwrap();
    assert!(!info.complete);
    assert!(info.render().contains("truncated: no summary"), "{}", info.render());
    let (entries, reader) = read_all(&[path]);
    assert_eq!(reader.truncated().len(), 1);
    let setpoints: Vec<_> = entries.iter().filter(|e| e.topic == "/control/setpoint").collect();
    assert!(setpoints.len() as u64 >= FLUSHED_SETPOINTS, "only {} set-points recovered", setpoints.len());
    for (i, e) in setpoints.iter().enumerate() {
        assert_eq!(e.sequence as usize, i, "sequence gap");
        assert_eq!(e.event, LogEvent::Setpoint(sample::setpoint(i as u64)));
    }
    assert_eq!(entries.iter().filter(|e| e.topic == "/base/odometry").count() as u64, FLUSHED_SETPOINTS);
}

#[test]
fn a_flooded_logger_drops_only_images_and_writes_the_counts_into_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("flood.mcap");
    let mut options = LogOptions::new("sim");
    options.image_queue = 2;
    let writer = LogWriter::create_at(&path, options).unwrap();
    let n = 300u64;
    let big = sample::frame(0, 640, 480);
    for i in 0..n {
        writer.image_mono8(i * sample::FRAME_NS, &big);
        writer.setpoint(i * sample::FRAME_NS, &sample::setpoint(i));
        writer.odometry(&sample::odometry(2 * i));
    }
    let summary = writer.close().unwrap();
    let s = &summary.stats;
    assert_eq!(summary.per_topic["/camera/image"] + s.dropped_images, n);
    assert_eq!((summary.per_topic["/control/setpoint"], summary.per_topic["/base/odometry"]), (n, n));
    assert_eq!((s.dropped_data, s.dropped_critical, s.lost), (0, 0, 0));
    let info = LogInfo::read(&path).unwrap();
    assert!(info.stats_final, "{}", info.render());
    assert_eq!(info.stats.as_ref().unwrap().dropped_images, s.dropped_images);
    assert!(info.render().contains(&format!("drops:     {} images", s.dropped_images)));
}
