//! # flownav-fnp: the FNP/1 codec, for the host and for firmware
//!
//! `#![no_std]`, no allocator: every buffer is a fixed array sized by the protocol's limits
//! ([`MAX_PACKET`], [`MAX_FRAME`]). The same code runs in flownav's host driver
//! (`hal::fnp_driver`), in the simulated base, and on a microcontroller
//! (`examples/fnp_firmware/` is a firmware main loop to port).
//!
//! - [`encode`] turns a [`Packet`] into frame bytes, delimiter included, in an [`Encoded`] buffer
//!   on the stack.
//! - A [`Decoder`] takes received bytes in any split, one at a time ([`Decoder::push`], what a
//!   UART interrupt or a polling loop has) or in chunks ([`Decoder::feed`]), and yields the valid
//!   frames; every dropped frame is counted by reason, every sequence gap as lost packets
//!   ([`DecodeStats`]). It never panics, whatever the input.
//! - CRC-16/CCITT-FALSE comes from the `crc` crate, COBS from the `cobs` crate.
//!
//! The optional `alloc` feature adds [`Decoder::feed_collect`] for hosts.
//!
//! The specification follows; it is `docs/protocol.md` in the repository, the single source, and
//! the crate's tests check its test vectors byte for byte.
//!
#![doc = include_str!("../../../docs/protocol.md")]
#![no_std]

#[cfg(feature = "alloc")]
extern crate alloc;

/// Largest packet before COBS: `type | seq | payload | crc`.
pub const MAX_PACKET: usize = 64;
/// Largest COBS-encoded packet without its delimiter (one code byte per 254 data bytes).
pub const MAX_ENCODED: usize = MAX_PACKET + MAX_PACKET.div_ceil(254);
/// Largest frame on the wire: an encoded packet and its `0x00` delimiter.
pub const MAX_FRAME: usize = MAX_ENCODED + 1;
/// Longest INFO name in bytes.
pub const MAX_NAME: usize = 16;
/// Protocol version reported in INFO by bases that implement this document.
pub const VERSION: u8 = 1;

// The encoder writes into MAX_ENCODED bytes; the cobs crate's bound must agree.
const _: () = assert!(cobs::max_encoding_length(MAX_PACKET) <= MAX_ENCODED);

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

/// An INFO name: ASCII, at most [`MAX_NAME`] bytes.
pub type Name = heapless::String<MAX_NAME>;

/// The bytes of one frame, delimiter included, as [`encode`] makes them.
pub type Encoded = heapless::Vec<u8, MAX_FRAME>;

/// `s` as an INFO name: its ASCII characters, the first [`MAX_NAME`] of them.
pub fn ascii_name(s: &str) -> Name {
    s.chars().filter(char::is_ascii).take(MAX_NAME).collect()
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
    /// Base → host: answer to HELLO. `name` is ASCII ([`ascii_name`] makes one from any text).
    Info { version: u8, wheel_base_mm: u16, ticks_per_m: u32, name: Name },
}

/// Which side a decoder listens to: packets of the other direction count as unknown types.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Direction {
    /// Packets the host sends (SETPOINT, STOP, HELLO): what a base decodes.
    HostToBase,
    /// Packets a base sends (ODOM, STATUS, INFO): what the host decodes.
    BaseToHost,
}

/// Appends little-endian fields to a fixed packet buffer.
struct Writer {
    buf: [u8; MAX_PACKET],
    len: usize,
}

impl Writer {
    fn put(&mut self, bytes: &[u8]) {
        // Every packet type fits MAX_PACKET (INFO, the longest, is 27 bytes with its CRC); the
        // bound only keeps a future type from writing past the buffer.
        let n = bytes.len().min(MAX_PACKET - self.len);
        self.buf[self.len..self.len + n].copy_from_slice(&bytes[..n]);
        self.len += n;
    }

    fn bytes(&self) -> &[u8] {
        &self.buf[..self.len]
    }
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

    /// Which way this packet travels.
    pub fn direction(&self) -> Direction {
        if self.type_code() & 0x80 == 0 { Direction::HostToBase } else { Direction::BaseToHost }
    }

    fn write_payload(&self, w: &mut Writer) {
        match self {
            Packet::Setpoint { v_mm_s, omega_mrad_s } => {
                w.put(&v_mm_s.to_le_bytes());
                w.put(&omega_mrad_s.to_le_bytes());
            }
            Packet::Stop => {}
            Packet::Hello { watchdog_ms } => w.put(&watchdog_ms.to_le_bytes()),
            Packet::Odom { t_us, left_ticks, right_ticks, v_mm_s, omega_mrad_s } => {
                w.put(&t_us.to_le_bytes());
                w.put(&left_ticks.to_le_bytes());
                w.put(&right_ticks.to_le_bytes());
                w.put(&v_mm_s.to_le_bytes());
                w.put(&omega_mrad_s.to_le_bytes());
            }
            Packet::Status { battery_mv, flags, last_seq } => {
                w.put(&battery_mv.to_le_bytes());
                w.put(&[*flags, *last_seq]);
            }
            Packet::Info { version, wheel_base_mm, ticks_per_m, name } => {
                w.put(&[*version]);
                w.put(&wheel_base_mm.to_le_bytes());
                w.put(&ticks_per_m.to_le_bytes());
                w.put(name.as_bytes());
            }
        }
    }

    /// Parses the payload of a packet of type `type_code`.
    fn parse(type_code: u8, p: &[u8]) -> Result<Packet, DropReason> {
        let i16_at = |i: usize| i16::from_le_bytes([p[i], p[i + 1]]);
        let u16_at = |i: usize| u16::from_le_bytes([p[i], p[i + 1]]);
        let u32_at = |i: usize| u32::from_le_bytes([p[i], p[i + 1], p[i + 2], p[i + 3]]);
        // Every index above is checked against the length first.
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
                // ASCII is UTF-8, and the length was checked: neither conversion can fail.
                let name = core::str::from_utf8(&p[7..]).ok().and_then(|s| Name::try_from(s).ok());
                let name = name.ok_or(DropReason::BadLength)?;
                Ok(Packet::Info { version: p[0], wheel_base_mm: u16_at(1), ticks_per_m: u32_at(3), name })
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

/// CRC-16/CCITT-FALSE (the catalogue's CRC-16/IBM-3740): poly 0x1021, init 0xFFFF, no
/// reflection, xorout 0; check("123456789") = 0x29B1.
const CRC16: crc::Crc<u16> = crc::Crc::<u16>::new(&crc::CRC_16_IBM_3740);

/// The FNP/1 CRC of `bytes` (over `type | seq | payload`).
pub fn crc16(bytes: &[u8]) -> u16 {
    CRC16.checksum(bytes)
}

/// The frame bytes for a packet, delimiter included: `COBS(type | seq | payload | crc LE) 0x00`.
pub fn encode(seq: u8, packet: &Packet) -> Encoded {
    let mut w = Writer { buf: [0; MAX_PACKET], len: 0 };
    w.put(&[packet.type_code(), seq]);
    packet.write_payload(&mut w);
    let crc = crc16(w.bytes());
    w.put(&crc.to_le_bytes());
    let mut out = Encoded::from_array([0; MAX_FRAME]);
    // Cannot panic: MAX_ENCODED bytes hold any encoded packet (checked at compile time above).
    let n = cobs::encode(w.bytes(), &mut out[..MAX_ENCODED]);
    // out[n], already zero, is the delimiter.
    out.truncate(n + 1);
    out
}

/// Like [`encode`], appending the frame to `out` (a `Vec<u8>`, a `heapless::Vec`, …).
pub fn encode_into(seq: u8, packet: &Packet, out: &mut impl Extend<u8>) {
    out.extend(encode(seq, packet));
}

/// Decodes one frame's bytes (without the delimiter) received from `dir`.
pub fn decode_frame(encoded: &[u8], dir: Direction) -> Result<Frame, DropReason> {
    if encoded.len() > MAX_ENCODED {
        return Err(DropReason::Oversize);
    }
    let mut raw = [0u8; MAX_PACKET];
    let n = cobs::decode(encoded, &mut raw).map_err(|_| DropReason::BadCobs)?.frame_size();
    let raw = &raw[..n];
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

/// An incremental FNP/1 receiver: give it bytes as they arrive, in any split.
///
/// Bytes accumulate until a `0x00` delimiter; each complete frame is decoded or dropped and
/// counted. More than [`MAX_ENCODED`] bytes without a delimiter are discarded up to the next
/// `0x00`, where the decoder resynchronises. Never panics, whatever the input. It holds one
/// frame's worth of bytes (about 150 bytes in all), so a firmware can keep it in a static.
#[derive(Clone, Debug)]
pub struct Decoder {
    dir: Direction,
    buf: heapless::Vec<u8, MAX_ENCODED>,
    overflowed: bool,
    last_seq: Option<u8>,
    stats: DecodeStats,
}

impl Decoder {
    /// A decoder for packets travelling in `dir`.
    pub const fn new(dir: Direction) -> Self {
        Self { dir, buf: heapless::Vec::new(), overflowed: false, last_seq: None, stats: Self::ZERO_STATS }
    }

    const ZERO_STATS: DecodeStats = DecodeStats {
        frames: 0,
        bad_cobs: 0,
        bad_crc: 0,
        unknown_type: 0,
        bad_length: 0,
        oversize: 0,
        lost: 0,
        seq_resyncs: 0,
    };

    /// Takes one received byte; returns the frame it completed, if it completed a valid one.
    pub fn push(&mut self, byte: u8) -> Option<Frame> {
        if byte != 0 {
            if self.buf.push(byte).is_err() && !self.overflowed {
                self.overflowed = true;
                self.stats.count(DropReason::Oversize);
            }
            return None;
        }
        let mut frame = None;
        if self.overflowed {
            self.overflowed = false;
        } else if !self.buf.is_empty() {
            match decode_frame(&self.buf, self.dir) {
                Ok(f) => {
                    self.track_seq(f.seq);
                    self.stats.frames += 1;
                    frame = Some(f);
                }
                Err(why) => self.stats.count(why),
            }
        }
        self.buf.clear();
        frame
    }

    /// Takes received bytes, calling `on_frame` for each valid frame completed by them.
    pub fn feed(&mut self, bytes: &[u8], mut on_frame: impl FnMut(Frame)) {
        for &b in bytes {
            if let Some(f) = self.push(b) {
                on_frame(f);
            }
        }
    }

    /// Takes received bytes and returns the frames they completed.
    #[cfg(feature = "alloc")]
    pub fn feed_collect(&mut self, bytes: &[u8]) -> alloc::vec::Vec<Frame> {
        let mut frames = alloc::vec::Vec::new();
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
