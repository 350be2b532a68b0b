//! The codec against the specification's test vectors (read from docs/protocol.md, the single
//! source), drop counting, sequence tracking, and property tests over arbitrary packets and bytes.

use fnp::{Decoder, Direction, DropReason, Frame, Packet, ascii_name, crc16, decode_frame, encode, flags, kind};
use proptest::prelude::*;

const SPEC: &str = include_str!("../../../docs/protocol.md");

fn hex(s: &str) -> Vec<u8> {
    s.split_whitespace().map(|h| u8::from_str_radix(h, 16).unwrap()).collect()
}

/// The frames of the spec's "Test vectors" section, in order: the first line of each fenced block.
fn spec_frames() -> Vec<Vec<u8>> {
    let section = SPEC.split("## Test vectors").nth(1).expect("docs/protocol.md has a 'Test vectors' section");
    let mut frames = Vec::new();
    let mut lines = section.lines();
    while let Some(line) = lines.next() {
        if line.trim() == "```text" {
            frames.push(hex(lines.next().expect("a hex line after ```text")));
        }
    }
    frames
}

/// The packets the spec's vectors describe, in the spec's order: (seq, packet).
fn spec_packets() -> Vec<(u8, Packet)> {
    vec![
        (7, Packet::Setpoint { v_mm_s: 300, omega_mrad_s: -150 }),
        (0, Packet::Setpoint { v_mm_s: 0, omega_mrad_s: 0 }),
        (8, Packet::Stop),
        (1, Packet::Hello { watchdog_ms: 250 }),
        (42, Packet::Odom { t_us: 1_000_000, left_ticks: 1234, right_ticks: -56, v_mm_s: 250, omega_mrad_s: 100 }),
        (3, Packet::Status { battery_mv: 12600, flags: flags::BUMPER | flags::WATCHDOG_STOP, last_seq: 7 }),
        (0, Packet::Info { version: 1, wheel_base_mm: 330, ticks_per_m: 10000, name: ascii_name("sim") }),
    ]
}

fn vectors() -> Vec<(u8, Packet, Vec<u8>)> {
    let frames = spec_frames();
    let packets = spec_packets();
    assert_eq!(
        frames.len(),
        packets.len(),
        "docs/protocol.md lists {} vectors, the test knows {}",
        frames.len(),
        packets.len()
    );
    packets.into_iter().zip(frames).map(|((seq, p), f)| (seq, p, f)).collect()
}

fn collect(d: &mut Decoder, bytes: &[u8]) -> Vec<Frame> {
    let mut got = Vec::new();
    d.feed(bytes, |f| got.push(f));
    got
}

#[test]
fn crc_check_value() {
    assert_eq!(crc16(b"123456789"), 0x29B1);
}

#[test]
fn spec_vectors_encode_byte_for_byte() {
    for (seq, packet, bytes) in vectors() {
        assert_eq!(encode(seq, &packet).as_slice(), bytes.as_slice(), "{packet:?}");
    }
}

#[test]
fn spec_vectors_decode_byte_for_byte() {
    for (seq, packet, bytes) in vectors() {
        let dir = packet.direction();
        let mut d = Decoder::new(dir);
        assert_eq!(collect(&mut d, &bytes), vec![Frame { seq, packet: packet.clone() }]);
        // One byte at a time gives the same.
        let mut d = Decoder::new(dir);
        let got: Vec<Frame> = bytes.iter().filter_map(|&b| d.push(b)).collect();
        assert_eq!(got, vec![Frame { seq, packet }]);
    }
}

#[test]
fn wrong_direction_is_unknown_type() {
    let (_, _, odom) = vectors().remove(4);
    let mut d = Decoder::new(Direction::HostToBase);
    assert!(collect(&mut d, &odom).is_empty());
    assert_eq!(d.stats().unknown_type, 1);
}

fn encode_raw(body: &[u8]) -> Vec<u8> {
    let mut raw = body.to_vec();
    raw.extend_from_slice(&crc16(body).to_le_bytes());
    let mut out = vec![0; cobs::max_encoding_length(raw.len())];
    let n = cobs::encode(&raw, &mut out);
    out.truncate(n);
    out.push(0);
    out
}

#[test]
fn drops_are_counted_by_kind() {
    let mut d = Decoder::new(Direction::HostToBase);
    // Bad CRC: flip a payload bit of the STOP vector.
    assert!(collect(&mut d, &hex("05 02 08 65 fb 00")).is_empty());
    assert_eq!(d.stats().bad_crc, 1);
    // Bad COBS: the code byte points past the end of the frame.
    assert!(collect(&mut d, &hex("09 02 08 00")).is_empty());
    assert_eq!(d.stats().bad_cobs, 1);
    // Unknown type 0x7f with a valid CRC.
    assert!(collect(&mut d, &encode_raw(&[0x7f, 1])).is_empty());
    assert_eq!(d.stats().unknown_type, 1);
    // SETPOINT with a 3-byte payload.
    assert!(collect(&mut d, &encode_raw(&[kind::SETPOINT, 2, 1, 2, 3])).is_empty());
    assert_eq!(d.stats().bad_length, 1);
    // 200 non-zero bytes: one oversize, discarded up to the next 0x00, then resync.
    assert!(collect(&mut d, &[0x55; 200]).is_empty());
    assert!(collect(&mut d, &hex("05 02 08 65 fa 00")).is_empty(), "frame inside discarded garbage accepted");
    assert_eq!(collect(&mut d, &hex("05 02 08 65 fa 00")).len(), 1);
    let s = d.stats();
    assert_eq!((s.oversize, s.frames, s.dropped()), (1, 1, 5));
}

#[test]
fn info_names_are_ascii_and_bounded() {
    assert_eq!(ascii_name("flownav-sim"), "flownav-sim");
    assert_eq!(ascii_name("base-ü-with-a-long-name"), "base--with-a-lon");
    // A non-ASCII name on the wire is a bad payload.
    let frame = encode_raw(&[kind::INFO, 0, 1, 0x4a, 0x01, 0x10, 0x27, 0, 0, 0xc3, 0xbc]);
    let without_delimiter = &frame[..frame.len() - 1];
    assert_eq!(decode_frame(without_delimiter, Direction::BaseToHost), Err(DropReason::BadLength));
}

#[test]
fn sequence_gaps_count_as_lost() {
    let mut d = Decoder::new(Direction::HostToBase);
    let mut bytes = Vec::new();
    for seq in [250u8, 251, 254, 255, 0, 3] {
        bytes.extend(encode(seq, &Packet::Stop));
    }
    assert_eq!(collect(&mut d, &bytes).len(), 6);
    assert_eq!(d.stats().lost, 2 + 2);
    // A restarted sender (seq jumps back) is a resync, not 250 lost packets.
    collect(&mut d, &encode(0, &Packet::Stop));
    assert_eq!((d.stats().lost, d.stats().seq_resyncs), (4, 1));
}

#[test]
fn encode_into_appends() {
    let mut out = vec![0xAA];
    fnp::encode_into(8, &Packet::Stop, &mut out);
    assert_eq!(out, hex("aa 05 02 08 65 fa 00"));
}

fn any_packet() -> impl Strategy<Value = Packet> {
    prop_oneof![
        (any::<i16>(), any::<i16>()).prop_map(|(v, w)| Packet::Setpoint { v_mm_s: v, omega_mrad_s: w }),
        Just(Packet::Stop),
        any::<u16>().prop_map(|w| Packet::Hello { watchdog_ms: w }),
        (any::<u32>(), any::<i32>(), any::<i32>(), any::<i16>(), any::<i16>()).prop_map(|(t, l, r, v, w)| {
            Packet::Odom { t_us: t, left_ticks: l, right_ticks: r, v_mm_s: v, omega_mrad_s: w }
        }),
        (any::<u16>(), any::<u8>(), any::<u8>()).prop_map(|(b, f, s)| Packet::Status {
            battery_mv: b,
            flags: f,
            last_seq: s
        }),
        (any::<u8>(), any::<u16>(), any::<u32>(), "[ -~]{0,16}").prop_map(|(v, wb, t, name)| Packet::Info {
            version: v,
            wheel_base_mm: wb,
            ticks_per_m: t,
            name: ascii_name(&name)
        }),
    ]
}

proptest! {
    #[test]
    fn round_trip(seq in any::<u8>(), packet in any_packet()) {
        let bytes = encode(seq, &packet);
        prop_assert_eq!(bytes.iter().filter(|&&b| b == 0).count(), 1);
        prop_assert_eq!(bytes.last(), Some(&0));
        prop_assert!(bytes.len() <= fnp::MAX_FRAME);
        let mut d = Decoder::new(packet.direction());
        prop_assert_eq!(collect(&mut d, &bytes), vec![Frame { seq, packet }]);
    }

    /// Arbitrary garbage never panics, and the first good frame after a 0x00 is decoded.
    #[test]
    fn garbage_then_resync(garbage in proptest::collection::vec(any::<u8>(), 0..400),
                           seq in any::<u8>(), packet in any_packet()) {
        let mut d = Decoder::new(packet.direction());
        collect(&mut d, &garbage);
        collect(&mut d, &[0]);
        prop_assert_eq!(collect(&mut d, &encode(seq, &packet)), vec![Frame { seq, packet }]);
    }

    #[test]
    fn no_panic_on_arbitrary_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..1000)) {
        for dir in [Direction::HostToBase, Direction::BaseToHost] {
            let mut d = Decoder::new(dir);
            let frames = collect(&mut d, &bytes);
            prop_assert!(frames.len() as u64 == d.stats().frames);
        }
    }
}
