//! Fuzzing of the decoders that take untrusted bytes: the FNP/1 and Kobuki serial decoders, the
//! MJPEG path (DHT insertion, then decoding), the MCAP reader behind `log info` and `replay`,
//! and the TOML loaders of the configuration, the map, the world and the calibration.
//!
//! A stable-toolchain harness: proptest with byte-level generators. Each target starts from a
//! seed corpus of valid inputs (frames, files) and mutates it (bit flips, byte overwrites,
//! insertions, deletions, duplicated runs, truncation), or wraps random bodies in a valid
//! envelope (COBS + CRC for FNP/1, header + XOR for Kobuki) so the packet parsers behind the
//! checksums are reached. The property is the same everywhere: the decoder returns (a value or
//! an error) and never panics.
//!
//! CI runs each target for proptest's default 256 cases (a few seconds in all, debug). A long
//! run: `PROPTEST_CASES=20000 cargo test --release --test fuzz`.

use flownav::logging::sample::{self, SampleImages};
use flownav::logging::{LogInfo, LogOptions, LogReader};
use hal::fnp::{self, Direction, Packet};
use hal::kobuki::{self, CoreSensors, KobukiDecoder};
use hal::mjpeg::MjpegDecoder;
use proptest::prelude::*;
use proptest::sample::Index;
use std::sync::OnceLock;

/// One edit of a seed input.
#[derive(Clone, Debug)]
enum Mutation {
    FlipBit(Index, u8),
    SetByte(Index, u8),
    Insert(Index, Vec<u8>),
    Delete(Index, usize),
    /// Copies a run of the input to another place (repeats markers, lengths, headers).
    Duplicate(Index, usize, Index),
    Truncate(Index),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        4 => (any::<Index>(), 0u8..8).prop_map(|(i, b)| Mutation::FlipBit(i, b)),
        3 => (any::<Index>(), any::<u8>()).prop_map(|(i, v)| Mutation::SetByte(i, v)),
        2 => (any::<Index>(), prop::collection::vec(any::<u8>(), 1..16)).prop_map(|(i, v)| Mutation::Insert(i, v)),
        2 => (any::<Index>(), 1usize..64).prop_map(|(i, n)| Mutation::Delete(i, n)),
        1 => (any::<Index>(), 1usize..64, any::<Index>()).prop_map(|(i, n, j)| Mutation::Duplicate(i, n, j)),
        1 => any::<Index>().prop_map(Mutation::Truncate),
    ]
}

fn apply(mut data: Vec<u8>, mutations: &[Mutation]) -> Vec<u8> {
    for m in mutations {
        if data.is_empty() {
            if let Mutation::Insert(_, v) = m {
                data.extend_from_slice(v);
            }
            continue;
        }
        let len = data.len();
        match m {
            Mutation::FlipBit(i, b) => data[i.index(len)] ^= 1 << b,
            Mutation::SetByte(i, v) => data[i.index(len)] = *v,
            Mutation::Insert(i, v) => {
                let at = i.index(len + 1);
                data.splice(at..at, v.iter().copied());
            }
            Mutation::Delete(i, n) => {
                let at = i.index(len);
                data.drain(at..(at + n).min(len));
            }
            Mutation::Duplicate(i, n, j) => {
                let from = i.index(len);
                let run = data[from..(from + n).min(len)].to_vec();
                let to = j.index(len + 1);
                data.splice(to..to, run);
            }
            Mutation::Truncate(i) => data.truncate(i.index(len)),
        }
    }
    data
}

/// A seed from `corpus` with up to `max_edits` mutations, or (one case in eight) random bytes.
fn mutated(corpus: &'static [Vec<u8>], max_edits: usize) -> impl Strategy<Value = Vec<u8>> {
    let edited = (any::<Index>(), prop::collection::vec(mutation(), 0..=max_edits))
        .prop_map(move |(i, edits)| apply(corpus[i.index(corpus.len())].clone(), &edits));
    prop_oneof![7 => edited, 1 => prop::collection::vec(any::<u8>(), 0..512)]
}

/// The same for text files: the mutated bytes as (lossy) UTF-8.
fn mutated_text(corpus: &'static [Vec<u8>]) -> impl Strategy<Value = String> {
    mutated(corpus, 6).prop_map(|b| String::from_utf8_lossy(&b).into_owned())
}

fn corpus(cell: &'static OnceLock<Vec<Vec<u8>>>, make: impl FnOnce() -> Vec<Vec<u8>>) -> &'static [Vec<u8>] {
    cell.get_or_init(make)
}

// ---- seed corpora ------------------------------------------------------------------------------

/// Encoded FNP/1 frames of every packet type in both directions, singly and as one stream.
fn fnp_corpus() -> &'static [Vec<u8>] {
    static C: OnceLock<Vec<Vec<u8>>> = OnceLock::new();
    corpus(&C, || {
        let packets = [
            Packet::Setpoint { v_mm_s: 250, omega_mrad_s: -300 },
            Packet::Stop,
            Packet::Hello { watchdog_ms: 300 },
            Packet::Odom { t_us: 1_234_567, left_ticks: -42_000, right_ticks: 41_000, v_mm_s: 180, omega_mrad_s: 25 },
            Packet::Status { battery_mv: 12_400, flags: 0x05, last_seq: 17 },
            Packet::Info { version: 1, wheel_base_mm: 230, ticks_per_m: 11_724, name: fnp::ascii_name("sim-base") },
        ];
        let mut frames: Vec<Vec<u8>> =
            packets.iter().enumerate().map(|(i, p)| fnp::encode(i as u8, p).to_vec()).collect();
        frames.push(frames.concat());
        frames
    })
}

/// Kobuki feedback frames (core sensors) and a base-control command, singly and as a stream.
fn kobuki_corpus() -> &'static [Vec<u8>] {
    static C: OnceLock<Vec<Vec<u8>>> = OnceLock::new();
    corpus(&C, || {
        let sensors = CoreSensors {
            timestamp_ms: 5000,
            bumper: 0x02,
            left_encoder: 61_000,
            right_encoder: 1200,
            left_pwm: -20,
            right_pwm: 20,
            battery_dv: 160,
            ..CoreSensors::default()
        };
        let mut frames = vec![kobuki::encode_frame(&sensors.to_subpayload()), kobuki::encode_base_control(200, -500)];
        frames.push(frames.concat());
        frames
    })
}

/// JPEG frames as `run` logs them, with their Huffman tables and without (the MJPEG form a UVC
/// camera sends, which the decoder completes with the standard DHT).
fn jpeg_corpus() -> &'static [Vec<u8>] {
    static C: OnceLock<Vec<Vec<u8>>> = OnceLock::new();
    corpus(&C, || {
        let with_dht = sample::jpeg_frame(3, 64, 48);
        let without = strip_dht(&with_dht);
        assert!(!hal::mjpeg::scan_markers(&without).unwrap().has_dht, "the MJPEG seed must lack its DHT");
        vec![with_dht, without]
    })
}

/// The JPEG without its DHT segments (the header walk stops at SOS).
fn strip_dht(jpeg: &[u8]) -> Vec<u8> {
    let mut out = jpeg[..2].to_vec();
    let mut i = 2;
    while i + 4 <= jpeg.len() && jpeg[i] == 0xFF {
        let marker = jpeg[i + 1];
        if marker == 0xDA {
            break;
        }
        let len = usize::from(u16::from_be_bytes([jpeg[i + 2], jpeg[i + 3]]));
        if marker != 0xC4 {
            out.extend_from_slice(&jpeg[i..i + 2 + len]);
        }
        i += 2 + len;
    }
    out.extend_from_slice(&jpeg[i..]);
    out
}

/// Small complete logs, one with mono8 frames and one with JPEG frames.
fn mcap_corpus() -> &'static [Vec<u8>] {
    static C: OnceLock<Vec<Vec<u8>>> = OnceLock::new();
    corpus(&C, || {
        let dir = tempfile::tempdir().unwrap();
        [SampleImages::Mono8, SampleImages::Jpeg]
            .into_iter()
            .enumerate()
            .map(|(i, images)| {
                let path = dir.path().join(format!("seed{i}.mcap"));
                let mut options = LogOptions::new("sim");
                // Small chunks: a mutation hits one chunk, the reader recovers the others.
                options.chunk_bytes = 4096;
                sample::write_sample(&path, 2, images, options).unwrap();
                std::fs::read(&path).unwrap()
            })
            .collect()
    })
}

fn text_corpus(cell: &'static OnceLock<Vec<Vec<u8>>>, texts: &[&str]) -> &'static [Vec<u8>] {
    let texts: Vec<Vec<u8>> = texts.iter().map(|t| t.as_bytes().to_vec()).collect();
    corpus(cell, || texts)
}

fn config_corpus() -> &'static [Vec<u8>] {
    static C: OnceLock<Vec<Vec<u8>>> = OnceLock::new();
    text_corpus(&C, &[include_str!("../config/robot.example.toml")])
}

fn map_corpus() -> &'static [Vec<u8>] {
    static C: OnceLock<Vec<Vec<u8>>> = OnceLock::new();
    text_corpus(&C, &[flownav::sim::OFFICE_MAP_TOML])
}

fn calib_corpus() -> &'static [Vec<u8>] {
    static C: OnceLock<Vec<Vec<u8>>> = OnceLock::new();
    text_corpus(&C, &[hal::calib::NOMINAL_C310_TOML, include_str!("../calib/wide90.toml")])
}

fn calib_import_corpus() -> &'static [Vec<u8>] {
    static C: OnceLock<Vec<Vec<u8>>> = OnceLock::new();
    text_corpus(
        &C,
        &[
            include_str!("../calib/examples/opencv-c310.yaml"),
            include_str!("../calib/examples/opencv-c310.xml"),
            include_str!("../calib/examples/ros-c310.yaml"),
        ],
    )
}

// ---- targets -----------------------------------------------------------------------------------

/// Writes `bytes` to a file in a fresh folder (the MCAP reader reads files).
fn as_file(bytes: &[u8]) -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("fuzz.mcap");
    std::fs::write(&path, bytes).unwrap();
    (dir, path)
}

proptest! {
    #[test]
    fn fnp_stream_decoder_never_panics(bytes in mutated(fnp_corpus(), 8), split in any::<Index>()) {
        for dir in [Direction::BaseToHost, Direction::HostToBase] {
            let mut decoder = fnp::Decoder::new(dir);
            // Fed in two pieces: a frame may straddle reads.
            let at = split.index(bytes.len() + 1);
            let mut frames = decoder.feed_collect(&bytes[..at]);
            frames.extend(decoder.feed_collect(&bytes[at..]));
            let stats = decoder.stats();
            prop_assert!(frames.len() as u64 <= stats.frames, "{} frames, stats {stats:?}", frames.len());
        }
    }

    #[test]
    fn fnp_packet_parser_behind_a_valid_crc_never_panics(
        type_code in any::<u8>(), seq in any::<u8>(), payload in prop::collection::vec(any::<u8>(), 0..40)
    ) {
        let mut raw = vec![type_code, seq];
        raw.extend_from_slice(&payload);
        raw.extend_from_slice(&fnp::crc16(&raw).to_le_bytes());
        let mut encoded = vec![0u8; cobs::max_encoding_length(raw.len())];
        let n = cobs::encode(&raw, &mut encoded);
        encoded.truncate(n);
        for dir in [Direction::BaseToHost, Direction::HostToBase] {
            if let Ok(frame) = fnp::decode_frame(&encoded, dir) {
                // What parses re-encodes to a frame that parses the same.
                let again = fnp::encode(frame.seq, &frame.packet);
                prop_assert_eq!(fnp::decode_frame(&again[..again.len() - 1], dir), Ok(frame));
            }
        }
    }

    #[test]
    fn kobuki_decoder_never_panics(bytes in mutated(kobuki_corpus(), 8)) {
        let mut decoder = KobukiDecoder::new();
        for payload in decoder.feed(&bytes) {
            let _ = decoder.core_sensors(&payload);
            let _ = decoder.base_control(&payload);
        }
    }

    #[test]
    fn kobuki_payload_parsers_behind_a_valid_checksum_never_panic(
        payload in prop_oneof![
            prop::collection::vec(any::<u8>(), 0..64),
            mutated(kobuki_corpus(), 4).prop_map(|f| f.get(3..f.len().saturating_sub(1)).unwrap_or_default().to_vec()),
        ]
    ) {
        let mut decoder = KobukiDecoder::new();
        for p in decoder.feed(&kobuki::encode_frame(&payload)) {
            let _ = decoder.core_sensors(&p);
            let _ = decoder.base_control(&p);
        }
    }

    #[test]
    fn mjpeg_decoder_never_panics(bytes in mutated(jpeg_corpus(), 6)) {
        // The size cap of a real camera stream: a corrupt header cannot make it allocate much.
        let mut decoder = MjpegDecoder::with_max_size(1920, 1080);
        if let Ok(image) = decoder.decode(&bytes) {
            prop_assert!(image.width() <= 1920 && image.height() <= 1080);
        }
    }

    #[test]
    fn mcap_reader_never_panics(bytes in mutated(mcap_corpus(), 4)) {
        let (_dir, path) = as_file(&bytes);
        if let Ok(reader) = LogReader::open(&path) {
            // Bounded: a mutation cannot make it yield more than the file could hold.
            for entry in reader.take(10_000) {
                if entry.is_err() {
                    break;
                }
            }
        }
        let _ = LogInfo::read(&path);
    }

    #[test]
    fn config_loader_never_panics(text in mutated_text(config_corpus())) {
        if let Ok(cfg) = toml::from_str::<flownav::config::Config>(&text) {
            let _ = cfg.validate();
        }
    }

    #[test]
    fn map_loader_never_panics(text in mutated_text(map_corpus())) {
        let _ = flownav::pafsis::TopoMap::parse(&text, "fuzz.toml");
    }

    #[test]
    fn world_loader_never_panics(text in mutated_text(world_corpus())) {
        let _ = mocks::world::World::from_toml(&text, "fuzz.toml");
    }

    #[test]
    fn calibration_loaders_never_panic(
        toml_text in mutated_text(calib_corpus()), imported in mutated_text(calib_import_corpus())
    ) {
        let _ = hal::Calibration::from_toml(&toml_text, "fuzz.toml");
        let _ = flownav::calib_import::import(&imported, "fuzz.yaml");
    }
}

fn world_corpus() -> &'static [Vec<u8>] {
    static C: OnceLock<Vec<Vec<u8>>> = OnceLock::new();
    text_corpus(&C, &[mocks::world::OFFICE_TOML])
}

#[test]
fn seed_corpora_are_valid_inputs() {
    // The mutations start from inputs every decoder accepts: otherwise they test error paths only.
    for frame in &fnp_corpus()[..6] {
        // One direction accepts the packet; the other counts it as an unknown type.
        let n: usize = [Direction::HostToBase, Direction::BaseToHost]
            .into_iter()
            .map(|dir| fnp::Decoder::new(dir).feed_collect(frame).len())
            .sum();
        assert_eq!(n, 1, "{frame:02x?}");
    }
    assert!(KobukiDecoder::new().core_sensors(&KobukiDecoder::new().feed(&kobuki_corpus()[0])[0]).is_some());
    for jpeg in jpeg_corpus() {
        let image = MjpegDecoder::new().decode(jpeg).unwrap();
        assert_eq!((image.width(), image.height()), (64, 48));
    }
    for file in mcap_corpus() {
        let (_dir, path) = as_file(file);
        assert!(LogInfo::read(&path).unwrap().complete, "{path:?}");
    }
    let cfg: flownav::config::Config = toml::from_str(std::str::from_utf8(&config_corpus()[0]).unwrap()).unwrap();
    cfg.validate().unwrap();
    flownav::pafsis::TopoMap::parse(flownav::sim::OFFICE_MAP_TOML, "office.toml").unwrap();
    mocks::world::World::from_toml(mocks::world::OFFICE_TOML, "office.toml").unwrap();
    for text in calib_import_corpus() {
        flownav::calib_import::import(std::str::from_utf8(text).unwrap(), "seed").unwrap();
    }
}
