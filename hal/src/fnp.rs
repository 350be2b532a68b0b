//! FNP/1, flownav's serial protocol (`PROTOCOL.md`): pure encoding and decoding over bytes.
//!
//! A frame on the wire is `COBS(type | seq | payload | crc16 LE) 0x00`. This module knows nothing
//! about ports or time: [`encode`] turns a packet into frame bytes, and a [`Decoder`] is fed
//! whatever bytes arrived (any split, any garbage) and yields the valid frames, counting every
//! dropped one by kind and every sequence gap as lost packets. The host driver
//! ([`crate::fnp_driver`]) and the simulated base in `mocks/` both sit on top of it.

/// Largest packet before COBS: `type | seq | payload | crc`.
pub const MAX_PACKET: usize = 64;
/// Largest COBS-encoded packet without its delimiter (one code byte per 254 data bytes).
pub const MAX_ENCODED: usize = MAX_PACKET + MAX_PACKET.div_ceil(254);
/// Longest INFO name in bytes.
pub const MAX_NAME: usize = 16;
/// Protocol version reported in INFO by bases that implement this document.
pub const VERSION: u8 = 1;

/// Packet type codes.
pub mod kind {
    pub const SETPOINT: u8 = 0x01;
    pub const STOP: u8 = 0x02;
    pub const HELLO: u8 = 0x03;
    pub const ODOM: u8 = 0x81;
    pub const STATUS: u8 = 0x82;
    pub const INFO: u8 = 0x83;
}

/// STATUS flag bits.
pub mod flags {
    pub const BUMPER: u8 = 1 << 0;
    pub const ESTOP: u8 = 1 << 1;
    pub const WATCHDOG_STOP: u8 = 1 << 2;
    pub const MOTOR_FAULT: u8 = 1 << 3;
}

/// One FNP/1 packet, fields in the protocol's own units (mm/s, mrad/s, µs, mV).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Packet {
    /// Host → base: drive at this body velocity.
    Setpoint { v_mm_s: i16, omega_mrad_s: i16 },
    /// Host → base: stop now.
    Stop,
    /// Host → base: set the watchdog; the base answers with INFO.
    Hello { watchdog_ms: u16 },
    /// Base → host: base clock, cumulative encoder counts, measured body velocity.
    Odom { t_us: u32, left_ticks: i32, right_ticks: i32, v_mm_s: i16, omega_mrad_s: i16 },
    /// Base → host: battery, [`flags`], last host sequence number received.
    Status { battery_mv: u16, flags: u8, last_seq: u8 },
    /// Base → host: answer to HELLO. `name` is ASCII, at most [`MAX_NAME`] bytes.
    Info { version: u8, wheel_base_mm: u16, ticks_per_m: u32, name: String },
}

/// Which side a decoder listens to: packets of the other direction count as unknown types.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Direction {
    /// Packets the host sends (SETPOINT, STOP, HELLO): what a base decodes.
    HostToBase,
    /// Packets a base sends (ODOM, STATUS, INFO): what the host decodes.
    BaseToHost,
}

impl Packet {
    pub fn type_code(&self) -> u8 {
        match self {
            Packet::Setpoint { .. } => kind::SETPOINT,
            Packet::Stop => kind::STOP,
            Packet::Hello { .. } => kind::HELLO,
            Packet::Odom { .. } => kind::ODOM,
            Packet::Status { .. } => kind::STATUS,
            Packet::Info { .. } => kind::INFO,
        }
    }

    /// Appends the payload bytes (little-endian fields).
    fn write_payload(&self, out: &mut Vec<u8>) {
        match self {
            Packet::Setpoint { v_mm_s, omega_mrad_s } => {
                out.extend_from_slice(&v_mm_s.to_le_bytes());
                out.extend_from_slice(&omega_mrad_s.to_le_bytes());
            }
            Packet::Stop => {}
            Packet::Hello { watchdog_ms } => out.extend_from_slice(&watchdog_ms.to_le_bytes()),
            Packet::Odom { t_us, left_ticks, right_ticks, v_mm_s, omega_mrad_s } => {
                out.extend_from_slice(&t_us.to_le_bytes());
                out.extend_from_slice(&left_ticks.to_le_bytes());
                out.extend_from_slice(&right_ticks.to_le_bytes());
                out.extend_from_slice(&v_mm_s.to_le_bytes());
                out.extend_from_slice(&omega_mrad_s.to_le_bytes());
            }
            Packet::Status { battery_mv, flags, last_seq } => {
                out.extend_from_slice(&battery_mv.to_le_bytes());
                out.push(*flags);
                out.push(*last_seq);
            }
            Packet::Info { version, wheel_base_mm, ticks_per_m, name } => {
                out.push(*version);
                out.extend_from_slice(&wheel_base_mm.to_le_bytes());
                out.extend_from_slice(&ticks_per_m.to_le_bytes());
                let name = name.as_bytes();
                out.extend_from_slice(&name[..name.len().min(MAX_NAME)]);
            }
        }
    }

    /// Parses a payload of a known type; `None` when its length is wrong for the type.
    fn parse(type_code: u8, p: &[u8]) -> Result<Packet, DropReason> {
        let i16_at = |i: usize| i16::from_le_bytes([p[i], p[i + 1]]);
        let u16_at = |i: usize| u16::from_le_bytes([p[i], p[i + 1]]);
        let u32_at = |i: usize| u32::from_le_bytes([p[i], p[i + 1], p[i + 2], p[i + 3]]);
        let need = |n: usize| if p.len() == n { Ok(()) } else { Err(DropReason::BadLength) };
        match type_code {
            kind::SETPOINT => need(4).map(|_| Packet::Setpoint { v_mm_s: i16_at(0), omega_mrad_s: i16_at(2) }),
            kind::STOP => need(0).map(|_| Packet::Stop),
            kind::HELLO => need(2).map(|_| Packet::Hello { watchdog_ms: u16_at(0) }),
            kind::ODOM => need(16).map(|_| Packet::Odom {
                t_us: u32_at(0),
                left_ticks: u32_at(4) as i32,
                right_ticks: u32_at(8) as i32,
                v_mm_s: i16_at(12),
                omega_mrad_s: i16_at(14),
            }),
            kind::STATUS => need(4).map(|_| Packet::Status { battery_mv: u16_at(0), flags: p[2], last_seq: p[3] }),
            kind::INFO => {
                if p.len() < 7 || p.len() > 7 + MAX_NAME || !p[7..].is_ascii() {
                    return Err(DropReason::BadLength);
                }
                Ok(Packet::Info {
                    version: p[0],
                    wheel_base_mm: u16_at(1),
                    ticks_per_m: u32_at(3),
                    name: String::from_utf8_lossy(&p[7..]).into_owned(),
                })
            }
            _ => Err(DropReason::UnknownType),
        }
    }
}

/// A decoded packet with the sender's sequence number.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Frame {
    pub seq: u8,
    pub packet: Packet,
}

/// Why a frame was dropped.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum DropReason {
    /// The COBS blocks do not add up (a code byte points past the end of the frame).
    BadCobs,
    /// The CRC does not match, or the frame is too short to hold one.
    BadCrc,
    /// A type code this side does not accept.
    UnknownType,
    /// The payload length does not fit the type (or an INFO name is not ASCII).
    BadLength,
    /// More than [`MAX_ENCODED`] bytes without a delimiter.
    Oversize,
}

/// CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, xorout 0 (check("123456789") = 0x29B1).
pub fn crc16(bytes: &[u8]) -> u16 {
    let mut crc: u16 = 0xFFFF;
    for &b in bytes {
        crc ^= u16::from(b) << 8;
        for _ in 0..8 {
            crc = if crc & 0x8000 != 0 { (crc << 1) ^ 0x1021 } else { crc << 1 };
        }
    }
    crc
}

/// Appends the COBS encoding of `data` (no delimiter) to `out`.
pub fn cobs_encode(data: &[u8], out: &mut Vec<u8>) {
    let mut code_at = out.len();
    out.push(0);
    let mut code: u8 = 1;
    for &b in data {
        if b == 0 {
            out[code_at] = code;
            code_at = out.len();
            out.push(0);
            code = 1;
        } else {
            out.push(b);
            code += 1;
            if code == 0xFF {
                out[code_at] = code;
                code_at = out.len();
                out.push(0);
                code = 1;
            }
        }
    }
    out[code_at] = code;
}

/// Decodes one COBS block sequence (no delimiter); `None` when it is malformed.
pub fn cobs_decode(data: &[u8], out: &mut Vec<u8>) -> Option<()> {
    out.clear();
    let mut i = 0;
    while i < data.len() {
        let code = data[i] as usize;
        if code == 0 || i + code > data.len() {
            return None;
        }
        out.extend_from_slice(&data[i + 1..i + code]);
        i += code;
        if code != 0xFF && i < data.len() {
            out.push(0);
        }
    }
    Some(())
}

/// The frame bytes for a packet, delimiter included: `COBS(type | seq | payload | crc LE) 0x00`.
pub fn encode(seq: u8, packet: &Packet) -> Vec<u8> {
    let mut out = Vec::with_capacity(MAX_ENCODED + 1);
    encode_into(seq, packet, &mut out);
    out
}

/// Like [`encode`], appending to `out` (no allocation when it has room).
pub fn encode_into(seq: u8, packet: &Packet, out: &mut Vec<u8>) {
    let mut raw = Vec::with_capacity(MAX_PACKET);
    raw.push(packet.type_code());
    raw.push(seq);
    packet.write_payload(&mut raw);
    let crc = crc16(&raw);
    raw.extend_from_slice(&crc.to_le_bytes());
    cobs_encode(&raw, out);
    out.push(0);
}

/// Decodes one frame's bytes (without the delimiter) received from `dir`.
pub fn decode_frame(encoded: &[u8], dir: Direction) -> Result<Frame, DropReason> {
    let mut raw = Vec::with_capacity(MAX_PACKET);
    decode_with(encoded, dir, &mut raw)
}

fn decode_with(encoded: &[u8], dir: Direction, raw: &mut Vec<u8>) -> Result<Frame, DropReason> {
    if encoded.len() > MAX_ENCODED {
        return Err(DropReason::Oversize);
    }
    cobs_decode(encoded, raw).ok_or(DropReason::BadCobs)?;
    if raw.len() < 4 {
        return Err(DropReason::BadCrc);
    }
    let (body, crc) = raw.split_at(raw.len() - 2);
    if crc16(body) != u16::from_le_bytes([crc[0], crc[1]]) {
        return Err(DropReason::BadCrc);
    }
    let type_code = body[0];
    let accepted = match dir {
        Direction::HostToBase => type_code & 0x80 == 0,
        Direction::BaseToHost => type_code & 0x80 != 0,
    };
    if !accepted {
        return Err(DropReason::UnknownType);
    }
    let packet = Packet::parse(type_code, &body[2..])?;
    Ok(Frame { seq: body[1], packet })
}

/// What a [`Decoder`] has seen: good frames, dropped frames by reason, and sequence gaps.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DecodeStats {
    /// Valid frames delivered.
    pub frames: u64,
    pub bad_cobs: u64,
    pub bad_crc: u64,
    pub unknown_type: u64,
    pub bad_length: u64,
    pub oversize: u64,
    /// Packets missing according to the sender's `seq` (gaps of 1..=127).
    pub lost: u64,
    /// Sequence jumps too large to be loss (a restarted sender, a duplicate): not counted as lost.
    pub seq_resyncs: u64,
}

impl DecodeStats {
    /// All frames dropped for any reason.
    pub fn dropped(&self) -> u64 {
        self.bad_cobs + self.bad_crc + self.unknown_type + self.bad_length + self.oversize
    }

    fn count(&mut self, why: DropReason) {
        match why {
            DropReason::BadCobs => self.bad_cobs += 1,
            DropReason::BadCrc => self.bad_crc += 1,
            DropReason::UnknownType => self.unknown_type += 1,
            DropReason::BadLength => self.bad_length += 1,
            DropReason::Oversize => self.oversize += 1,
        }
    }
}

/// An incremental FNP/1 receiver: feed it bytes as they arrive, in any split.
///
/// Bytes accumulate until a `0x00` delimiter; each complete frame is decoded or dropped and
/// counted. More than [`MAX_ENCODED`] bytes without a delimiter are discarded up to the next
/// `0x00`, where the decoder resynchronises. Never panics, whatever the input.
#[derive(Clone, Debug)]
pub struct Decoder {
    dir: Direction,
    buf: Vec<u8>,
    raw: Vec<u8>,
    overflowed: bool,
    last_seq: Option<u8>,
    stats: DecodeStats,
}

impl Decoder {
    /// A decoder for packets travelling in `dir`.
    pub fn new(dir: Direction) -> Self {
        Self {
            dir,
            buf: Vec::with_capacity(MAX_ENCODED),
            raw: Vec::with_capacity(MAX_PACKET),
            overflowed: false,
            last_seq: None,
            stats: DecodeStats::default(),
        }
    }

    /// Feeds bytes, calling `on_frame` for each valid frame completed by them.
    pub fn feed(&mut self, bytes: &[u8], mut on_frame: impl FnMut(Frame)) {
        for &b in bytes {
            if b != 0 {
                if self.buf.len() < MAX_ENCODED {
                    self.buf.push(b);
                } else if !self.overflowed {
                    self.overflowed = true;
                    self.stats.count(DropReason::Oversize);
                }
                continue;
            }
            if self.overflowed {
                self.overflowed = false;
            } else if !self.buf.is_empty() {
                match decode_with(&self.buf, self.dir, &mut self.raw) {
                    Ok(frame) => {
                        self.track_seq(frame.seq);
                        self.stats.frames += 1;
                        on_frame(frame);
                    }
                    Err(why) => self.stats.count(why),
                }
            }
            self.buf.clear();
        }
    }

    /// Feeds bytes and returns the frames they completed.
    pub fn feed_collect(&mut self, bytes: &[u8]) -> Vec<Frame> {
        let mut frames = Vec::new();
        self.feed(bytes, |f| frames.push(f));
        frames
    }

    fn track_seq(&mut self, seq: u8) {
        if let Some(last) = self.last_seq {
            let gap = seq.wrapping_sub(last).wrapping_sub(1);
            if gap < 128 {
                self.stats.lost += u64::from(gap);
            } else {
                self.stats.seq_resyncs += 1;
            }
        }
        self.last_seq = Some(seq);
    }

    /// Forgets a partial frame and the last sequence number (after a reconnect); keeps the counters.
    pub fn resync(&mut self) {
        self.buf.clear();
        self.overflowed = false;
        self.last_seq = None;
    }

    pub fn stats(&self) -> DecodeStats {
        self.stats
    }

    /// The sequence number of the last valid frame.
    pub fn last_seq(&self) -> Option<u8> {
        self.last_seq
    }
}

/// Saturating conversion of a value in SI units to a protocol integer (`scale` = units per SI unit).
pub fn to_i16_clamped(value: f64, scale: f64) -> i16 {
    let x = (value * scale).round();
    if x.is_nan() { 0 } else { x.clamp(f64::from(i16::MIN), f64::from(i16::MAX)) as i16 }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn hex(s: &str) -> Vec<u8> {
        s.split_whitespace().map(|h| u8::from_str_radix(h, 16).unwrap()).collect()
    }

    /// Every test vector of PROTOCOL.md: (seq, packet, direction, frame bytes).
    pub(crate) fn vectors() -> Vec<(u8, Packet, Direction, Vec<u8>)> {
        use Direction::*;
        vec![
            (7, Packet::Setpoint { v_mm_s: 300, omega_mrad_s: -150 }, HostToBase, hex("09 01 07 2c 01 6a ff 39 99 00")),
            (0, Packet::Setpoint { v_mm_s: 0, omega_mrad_s: 0 }, HostToBase, hex("02 01 01 01 01 01 03 b0 4b 00")),
            (8, Packet::Stop, HostToBase, hex("05 02 08 65 fa 00")),
            (1, Packet::Hello { watchdog_ms: 250 }, HostToBase, hex("04 03 01 fa 03 26 d4 00")),
            (
                42,
                Packet::Odom { t_us: 1_000_000, left_ticks: 1234, right_ticks: -56, v_mm_s: 250, omega_mrad_s: 100 },
                BaseToHost,
                hex("06 81 2a 40 42 0f 03 d2 04 01 06 c8 ff ff ff fa 02 64 03 38 21 00"),
            ),
            (
                3,
                Packet::Status { battery_mv: 12600, flags: flags::BUMPER | flags::WATCHDOG_STOP, last_seq: 7 },
                BaseToHost,
                hex("09 82 03 38 31 05 07 0f 6b 00"),
            ),
            (
                0,
                Packet::Info { version: 1, wheel_base_mm: 330, ticks_per_m: 10000, name: "sim".into() },
                BaseToHost,
                hex("02 83 06 01 4a 01 10 27 01 06 73 69 6d c3 f4 00"),
            ),
        ]
    }

    #[test]
    fn crc_check_value() {
        assert_eq!(crc16(b"123456789"), 0x29B1);
    }

    #[test]
    fn test_vectors_encode_byte_for_byte() {
        for (seq, packet, _, bytes) in vectors() {
            assert_eq!(encode(seq, &packet), bytes, "{packet:?}");
        }
    }

    #[test]
    fn test_vectors_decode_byte_for_byte() {
        for (seq, packet, dir, bytes) in vectors() {
            let mut d = Decoder::new(dir);
            let frames = d.feed_collect(&bytes);
            assert_eq!(frames, vec![Frame { seq, packet: packet.clone() }]);
            // One byte at a time gives the same.
            let mut d = Decoder::new(dir);
            let mut got = Vec::new();
            for b in &bytes {
                d.feed(std::slice::from_ref(b), |f| got.push(f));
            }
            assert_eq!(got, vec![Frame { seq, packet }]);
        }
    }

    #[test]
    fn wrong_direction_is_unknown_type() {
        let (_, _, _, odom) = vectors().remove(4);
        let mut d = Decoder::new(Direction::HostToBase);
        assert!(d.feed_collect(&odom).is_empty());
        assert_eq!(d.stats().unknown_type, 1);
    }

    #[test]
    fn drops_are_counted_by_kind() {
        let mut d = Decoder::new(Direction::HostToBase);
        // Bad CRC: flip a payload bit of the STOP vector.
        d.feed(&hex("05 02 08 65 fb 00"), |_| panic!("bad crc accepted"));
        assert_eq!(d.stats().bad_crc, 1);
        // Bad COBS: the code byte points past the end of the frame.
        d.feed(&hex("09 02 08 00"), |_| panic!());
        assert_eq!(d.stats().bad_cobs, 1);
        // Unknown type 0x7f with a valid CRC.
        d.feed(&encode_raw(&[0x7f, 1]), |_| panic!());
        assert_eq!(d.stats().unknown_type, 1);
        // SETPOINT with a 3-byte payload.
        d.feed(&encode_raw(&[kind::SETPOINT, 2, 1, 2, 3]), |_| panic!());
        assert_eq!(d.stats().bad_length, 1);
        // 200 non-zero bytes: one oversize, discarded up to the next 0x00, then resync.
        d.feed(&[0x55; 200], |_| panic!());
        d.feed(&hex("05 02 08 65 fa 00"), |_| panic!("frame inside discarded garbage accepted"));
        let got = d.feed_collect(&hex("05 02 08 65 fa 00"));
        assert_eq!(got.len(), 1);
        let s = d.stats();
        assert_eq!((s.oversize, s.frames, s.dropped()), (1, 1, 5));
    }

    fn encode_raw(body: &[u8]) -> Vec<u8> {
        let mut raw = body.to_vec();
        raw.extend_from_slice(&crc16(body).to_le_bytes());
        let mut out = Vec::new();
        cobs_encode(&raw, &mut out);
        out.push(0);
        out
    }

    #[test]
    fn sequence_gaps_count_as_lost() {
        let mut d = Decoder::new(Direction::HostToBase);
        let mut bytes = Vec::new();
        for seq in [250u8, 251, 254, 255, 0, 3] {
            bytes.extend(encode(seq, &Packet::Stop));
        }
        assert_eq!(d.feed_collect(&bytes).len(), 6);
        assert_eq!(d.stats().lost, 2 + 2);
        // A restarted sender (seq jumps back) is a resync, not 250 lost packets.
        d.feed(&encode(0, &Packet::Stop), |_| {});
        assert_eq!((d.stats().lost, d.stats().seq_resyncs), (4, 1));
    }

    #[test]
    fn clamping_to_i16() {
        assert_eq!(to_i16_clamped(0.3, 1000.0), 300);
        assert_eq!(to_i16_clamped(100.0, 1000.0), i16::MAX);
        assert_eq!(to_i16_clamped(-100.0, 1000.0), i16::MIN);
        assert_eq!(to_i16_clamped(f64::NAN, 1000.0), 0);
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
                name
            }),
        ]
    }

    fn dir_of(p: &Packet) -> Direction {
        if p.type_code() & 0x80 == 0 { Direction::HostToBase } else { Direction::BaseToHost }
    }

    proptest! {
        #[test]
        fn round_trip(seq in any::<u8>(), packet in any_packet()) {
            let bytes = encode(seq, &packet);
            prop_assert_eq!(bytes.iter().filter(|&&b| b == 0).count(), 1);
            prop_assert!(bytes.len() <= MAX_ENCODED + 1);
            let mut d = Decoder::new(dir_of(&packet));
            prop_assert_eq!(d.feed_collect(&bytes), vec![Frame { seq, packet }]);
        }

        #[test]
        fn cobs_round_trip(data in proptest::collection::vec(any::<u8>(), 0..600)) {
            let mut enc = Vec::new();
            cobs_encode(&data, &mut enc);
            prop_assert!(!enc.contains(&0));
            let mut dec = Vec::new();
            prop_assert!(cobs_decode(&enc, &mut dec).is_some());
            prop_assert_eq!(dec, data);
        }

        /// Arbitrary garbage never panics, and the first good frame after a 0x00 is decoded.
        #[test]
        fn garbage_then_resync(garbage in proptest::collection::vec(any::<u8>(), 0..400),
                               seq in any::<u8>(), packet in any_packet()) {
            let dir = dir_of(&packet);
            let mut d = Decoder::new(dir);
            d.feed(&garbage, |_| {});
            d.feed(&[0], |_| {});
            let got = d.feed_collect(&encode(seq, &packet));
            prop_assert_eq!(got, vec![Frame { seq, packet }]);
        }

        #[test]
        fn no_panic_on_arbitrary_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..1000)) {
            for dir in [Direction::HostToBase, Direction::BaseToHost] {
                let mut d = Decoder::new(dir);
                let frames = d.feed_collect(&bytes);
                prop_assert!(frames.len() as u64 == d.stats().frames);
            }
        }
    }
}
