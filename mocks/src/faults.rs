//! Fault injection on a simulated serial link, and the small seeded RNG the simulated bases use.
//!
//! A [`FaultInjector`] sits between a simulated base and its pty: each chunk of bytes may lose
//! bytes, get bytes corrupted (one random bit flipped) or be held back for a while; and the link
//! may go down now and then (the server closes the pty and opens a new one). Every fault is
//! counted, so tests can check that the driver survived exactly what was done to it.
//!
//! An [`AlarmWindow`] raises one of the base's own alarms (bumper, e-stop, cliff, wheel drop,
//! motor fault) for a while in the base's simulated time (`sim-base --alarm estop@2+1.5`).

use std::str::FromStr;
use std::time::Duration;

/// SplitMix64: tiny, seeded, reproducible; good enough for noise and fault draws.
#[derive(Clone, Debug)]
pub struct SimRng(u64);

impl SimRng {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Standard normal (Box–Muller).
    pub fn normal(&mut self) -> f64 {
        let u1 = self.uniform().max(f64::MIN_POSITIVE);
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// True with probability `p`.
    pub fn chance(&mut self, p: f64) -> bool {
        p > 0.0 && self.uniform() < p
    }
}

/// What to do to the link. All probabilities default to 0 (a perfect link).
#[derive(Clone, Debug, PartialEq)]
pub struct FaultConfig {
    /// Probability that a byte is lost.
    pub drop: f64,
    /// Probability that a byte has one bit flipped.
    pub corrupt: f64,
    /// Probability that a chunk is held back, for up to `delay_max`.
    pub delay: f64,
    pub delay_max: Duration,
    /// Expected disconnects per second of link time (a served pty draws them only while a
    /// driver has the port open); each lasts `disconnect_for`.
    pub disconnect_per_s: f64,
    pub disconnect_for: Duration,
    pub seed: u64,
}

impl Default for FaultConfig {
    fn default() -> Self {
        Self {
            drop: 0.0,
            corrupt: 0.0,
            delay: 0.0,
            delay_max: Duration::from_millis(20),
            disconnect_per_s: 0.0,
            disconnect_for: Duration::from_secs(1),
            seed: 1,
        }
    }
}

/// A bad `--faults` specification.
#[derive(Debug, thiserror::Error)]
#[error("--faults: {0} (expected e.g. \"drop=0.01,corrupt=0.005,delay=0.05:20ms,disconnect=0.02:1s,seed=7\")")]
pub struct FaultSpecError(String);

fn parse_duration(s: &str) -> Result<Duration, FaultSpecError> {
    let bad = || FaultSpecError(format!("bad duration '{s}' (use ms or s, e.g. 20ms, 1.5s)"));
    let (num, scale) = if let Some(n) = s.strip_suffix("ms") {
        (n, 1e-3)
    } else if let Some(n) = s.strip_suffix('s') {
        (n, 1.0)
    } else {
        return Err(bad());
    };
    let x: f64 = num.parse().map_err(|_| bad())?;
    if !(0.0..=3600.0).contains(&x) {
        return Err(bad());
    }
    Ok(Duration::from_secs_f64(x * scale))
}

fn parse_prob(key: &str, s: &str, max: f64) -> Result<f64, FaultSpecError> {
    match s.parse::<f64>() {
        Ok(p) if (0.0..=max).contains(&p) => Ok(p),
        _ => Err(FaultSpecError(format!("{key}={s} must be a number in 0..={max}"))),
    }
}

impl FromStr for FaultConfig {
    type Err = FaultSpecError;

    /// `key=value` pairs separated by commas: `drop=P`, `corrupt=P`, `delay=P[:MAX]`,
    /// `disconnect=RATE_PER_S[:FOR]`, `seed=N`. An empty string is a perfect link.
    fn from_str(spec: &str) -> Result<Self, Self::Err> {
        let mut cfg = FaultConfig::default();
        for (key, value) in crate::spec::items(spec) {
            let value = value.ok_or_else(|| FaultSpecError(format!("'{key}' is not key=value")))?;
            let (first, second) = match value.split_once(':') {
                Some((a, b)) => (a, Some(b)),
                None => (value, None),
            };
            match key {
                "drop" => cfg.drop = parse_prob(key, value, 1.0)?,
                "corrupt" => cfg.corrupt = parse_prob(key, value, 1.0)?,
                "delay" => {
                    cfg.delay = parse_prob(key, first, 1.0)?;
                    if let Some(d) = second {
                        cfg.delay_max = parse_duration(d)?;
                    }
                }
                "disconnect" => {
                    cfg.disconnect_per_s = parse_prob(key, first, 100.0)?;
                    if let Some(d) = second {
                        cfg.disconnect_for = parse_duration(d)?;
                    }
                }
                "seed" => {
                    cfg.seed = value.parse().map_err(|_| FaultSpecError(format!("seed={value} is not an integer")))?
                }
                _ => return Err(FaultSpecError(format!("unknown fault '{key}'"))),
            }
        }
        Ok(cfg)
    }
}

/// One of the alarms a base reports in its status.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum AlarmKind {
    Bumper,
    Estop,
    Cliff,
    WheelDrop,
    MotorFault,
}

impl AlarmKind {
    pub const ALL: [AlarmKind; 5] =
        [AlarmKind::Bumper, AlarmKind::Estop, AlarmKind::Cliff, AlarmKind::WheelDrop, AlarmKind::MotorFault];

    /// The name in an `--alarm` spec.
    pub fn name(self) -> &'static str {
        match self {
            AlarmKind::Bumper => "bumper",
            AlarmKind::Estop => "estop",
            AlarmKind::Cliff => "cliff",
            AlarmKind::WheelDrop => "wheel-drop",
            AlarmKind::MotorFault => "motor-fault",
        }
    }
}

/// An alarm raised from `start` for `duration` of the base's simulated time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AlarmWindow {
    pub kind: AlarmKind,
    pub start: Duration,
    pub duration: Duration,
}

impl AlarmWindow {
    /// Whether the alarm is raised at `t_s` (simulated seconds since the base started).
    pub fn active(&self, t_s: f64) -> bool {
        let start = self.start.as_secs_f64();
        t_s >= start && t_s < start + self.duration.as_secs_f64()
    }

    /// Whether any window of `kind` in `windows` is raised at `t_s`.
    pub fn any(windows: &[AlarmWindow], kind: AlarmKind, t_s: f64) -> bool {
        windows.iter().any(|w| w.kind == kind && w.active(t_s))
    }
}

/// A bad `--alarm` specification.
#[derive(Debug, thiserror::Error)]
#[error(
    "--alarm {spec}: {problem} (expected KIND@START+FOR, e.g. estop@2+1.5 or bumper@500ms+2s; KIND is one of bumper, estop, cliff, wheel-drop, motor-fault; times are seconds of the base's clock, or with ms/s)"
)]
pub struct AlarmSpecError {
    spec: String,
    problem: String,
}

impl FromStr for AlarmWindow {
    type Err = AlarmSpecError;

    /// `KIND@START+FOR`: `estop@2+1.5` raises the e-stop 2 s after the base started, for 1.5 s.
    fn from_str(spec: &str) -> Result<Self, Self::Err> {
        let bad = |problem: String| AlarmSpecError { spec: spec.into(), problem };
        let (kind, times) = spec.trim().split_once('@').ok_or_else(|| bad("no '@' before the start time".into()))?;
        let kind = AlarmKind::ALL
            .into_iter()
            .find(|k| k.name() == kind)
            .ok_or_else(|| bad(format!("unknown alarm '{kind}'")))?;
        let (start, duration) = times.split_once('+').ok_or_else(|| bad("no '+' before the duration".into()))?;
        let time = |s: &str| {
            let with_unit = if s.ends_with('s') { s.to_string() } else { format!("{s}s") };
            parse_duration(&with_unit).map_err(|e| bad(e.0))
        };
        let (start, duration) = (time(start)?, time(duration)?);
        if duration.is_zero() {
            return Err(bad("the duration must be more than 0".into()));
        }
        Ok(Self { kind, start, duration })
    }
}

/// Counts of every fault injected.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FaultStats {
    pub bytes_dropped: u64,
    pub bytes_corrupted: u64,
    pub chunks_delayed: u64,
    pub disconnects: u64,
    /// Frames (bytes up to a 0x00 delimiter, as FNP/1's COBS framing has them) that a dropped or
    /// corrupted byte made undeliverable. A lost or damaged delimiter merges its frame with the
    /// next, so both count: each is one packet missing from the sender's sequence, which is what
    /// a receiver counts.
    pub frames_hit: u64,
    /// Of `frames_hit`, those after the last intact frame when the link went down: no later frame
    /// reveals their sequence gap to a receiver that starts afresh on the new link.
    pub frames_hit_unseen: u64,
}

/// Applies a [`FaultConfig`] to chunks of bytes, deterministically for a given seed.
#[derive(Clone, Debug)]
pub struct FaultInjector {
    cfg: FaultConfig,
    rng: SimRng,
    stats: FaultStats,
    /// Whether the frame being passed through has lost or changed a byte.
    frame_hit: bool,
    /// Frames hit since the last intact frame.
    hit_since_intact: u64,
}

impl FaultInjector {
    pub fn new(cfg: FaultConfig) -> Self {
        let rng = SimRng::new(cfg.seed);
        Self { cfg, rng, stats: FaultStats::default(), frame_hit: false, hit_since_intact: 0 }
    }

    /// Ends the frame whose delimiter was just passed (`delimiter_hit`: it was dropped or changed).
    fn end_frame(&mut self, delimiter_hit: bool) {
        if self.frame_hit || delimiter_hit {
            self.stats.frames_hit += 1;
            self.hit_since_intact += 1;
        } else {
            self.hit_since_intact = 0;
        }
        // Without its delimiter the next frame runs into this one and is lost with it.
        self.frame_hit = delimiter_hit;
    }

    pub fn config(&self) -> &FaultConfig {
        &self.cfg
    }

    /// The bytes that make it through, and how long to hold them back first.
    pub fn apply(&mut self, bytes: &[u8]) -> (Vec<u8>, Option<Duration>) {
        let mut out = Vec::with_capacity(bytes.len());
        for &b in bytes {
            let hit = if self.rng.chance(self.cfg.drop) {
                self.stats.bytes_dropped += 1;
                true
            } else if self.rng.chance(self.cfg.corrupt) {
                self.stats.bytes_corrupted += 1;
                out.push(b ^ (1 << (self.rng.next_u64() % 8)));
                true
            } else {
                out.push(b);
                false
            };
            if b == 0 {
                self.end_frame(hit);
            } else {
                self.frame_hit |= hit;
            }
        }
        let delay = if self.rng.chance(self.cfg.delay) {
            self.stats.chunks_delayed += 1;
            Some(self.cfg.delay_max.mul_f64(self.rng.uniform()))
        } else {
            None
        };
        (out, delay)
    }

    /// Whether the link should go down during the next `dt` (Poisson with `disconnect_per_s`).
    pub fn disconnect_now(&mut self, dt: Duration) -> bool {
        let hit = self.rng.chance(self.cfg.disconnect_per_s * dt.as_secs_f64());
        if hit {
            self.count_disconnect();
        }
        hit
    }

    /// Records a disconnect that was asked for rather than drawn.
    pub fn count_disconnect(&mut self) {
        self.stats.disconnects += 1;
        self.link_down();
    }

    /// The link went down: a partial frame is gone, and hit frames that no intact frame followed
    /// stay unseen by the receiver.
    pub fn link_down(&mut self) {
        self.stats.frames_hit_unseen += self.hit_since_intact;
        self.hit_since_intact = 0;
        self.frame_hit = false;
    }

    pub fn stats(&self) -> FaultStats {
        self.stats
    }

    pub fn is_clean(&self) -> bool {
        self.cfg.drop == 0.0 && self.cfg.corrupt == 0.0 && self.cfg.delay == 0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_parses_and_rejects_nonsense() {
        let c: FaultConfig = "drop=0.01, corrupt=0.005,delay=0.05:30ms,disconnect=0.5:2s,seed=9".parse().unwrap();
        assert_eq!(c.drop, 0.01);
        assert_eq!(c.corrupt, 0.005);
        assert_eq!((c.delay, c.delay_max), (0.05, Duration::from_millis(30)));
        assert_eq!((c.disconnect_per_s, c.disconnect_for), (0.5, Duration::from_secs(2)));
        assert_eq!(c.seed, 9);
        assert_eq!("".parse::<FaultConfig>().unwrap(), FaultConfig::default());
        assert!("drop=2".parse::<FaultConfig>().unwrap_err().to_string().contains("drop=2"));
        assert!("bogus=1".parse::<FaultConfig>().unwrap_err().to_string().contains("unknown fault 'bogus'"));
        assert!("delay=0.1:5min".parse::<FaultConfig>().is_err());
    }

    #[test]
    fn alarm_specs_parse_and_reject_nonsense() {
        let w: AlarmWindow = "estop@2.0+1.5".parse().unwrap();
        assert_eq!(
            w,
            AlarmWindow {
                kind: AlarmKind::Estop,
                start: Duration::from_secs(2),
                duration: Duration::from_millis(1500)
            }
        );
        assert!(!w.active(1.999) && w.active(2.0) && w.active(3.499) && !w.active(3.5));
        let w: AlarmWindow = "wheel-drop@500ms+2s".parse().unwrap();
        assert_eq!(
            (w.kind, w.start, w.duration),
            (AlarmKind::WheelDrop, Duration::from_millis(500), Duration::from_secs(2))
        );
        for k in AlarmKind::ALL {
            assert_eq!(format!("{}@0+1", k.name()).parse::<AlarmWindow>().unwrap().kind, k);
        }
        let err = |s: &str| s.parse::<AlarmWindow>().unwrap_err().to_string();
        assert!(err("lava@1+1").contains("unknown alarm 'lava'"), "{}", err("lava@1+1"));
        assert!(err("estop+1").contains("no '@'"));
        assert!(err("estop@1").contains("no '+'"));
        assert!(err("estop@x+1").contains("bad duration"));
        assert!(err("estop@1+0").contains("more than 0"));
    }

    #[test]
    fn injected_faults_match_their_rates_and_are_counted() {
        let cfg = FaultConfig { drop: 0.1, corrupt: 0.05, ..Default::default() };
        let mut inj = FaultInjector::new(cfg);
        let input = vec![0xAAu8; 100_000];
        let (out, _) = inj.apply(&input);
        let s = inj.stats();
        assert_eq!(out.len() as u64, 100_000 - s.bytes_dropped);
        assert_eq!(out.iter().filter(|&&b| b != 0xAA).count() as u64, s.bytes_corrupted);
        assert!((9_000..11_000).contains(&s.bytes_dropped), "{s:?}");
        assert!((4_000..5_000).contains(&s.bytes_corrupted), "{s:?}");
        // Same seed, same faults.
        let mut again = FaultInjector::new(inj.config().clone());
        assert_eq!(again.apply(&input).0, out);
    }

    #[test]
    fn hit_frames_are_counted_as_a_receiver_counts_lost_packets() {
        use hal::fnp::{self, Decoder, Direction, Packet};
        let cfg = FaultConfig { drop: 0.01, corrupt: 0.01, seed: 5, ..Default::default() };
        let mut inj = FaultInjector::new(cfg);
        let mut rx = Decoder::new(Direction::BaseToHost);
        for seq in 0..=255u8 {
            // Chunks of two frames: a delimiter hit merges frames inside and across chunks.
            let status = Packet::Status { battery_mv: 12_000, flags: 0, last_seq: 0 };
            let mut bytes = fnp::encode(seq.wrapping_mul(2), &status).to_vec();
            bytes.extend_from_slice(&fnp::encode(seq.wrapping_mul(2).wrapping_add(1), &status));
            let (out, _) = inj.apply(&bytes);
            rx.feed(&out, |_| {});
        }
        // A last intact frame reveals the gaps before it.
        let last = Packet::Status { battery_mv: 12_000, flags: 0, last_seq: 0 };
        let (out, _) = FaultInjector::new(FaultConfig::default()).apply(&fnp::encode(0, &last));
        rx.feed(&out, |_| {});
        let s = inj.stats();
        assert!(s.frames_hit > 20, "{s:?}");
        assert_eq!(rx.stats().lost, s.frames_hit, "{s:?} {:?}", rx.stats());
        assert_eq!(rx.stats().frames, 512 + 1 - s.frames_hit);
    }

    #[test]
    fn rng_normal_has_unit_variance() {
        let mut r = SimRng::new(3);
        let xs: Vec<f64> = (0..20_000).map(|_| r.normal()).collect();
        let mean = xs.iter().sum::<f64>() / xs.len() as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / xs.len() as f64;
        assert!(mean.abs() < 0.03 && (var - 1.0).abs() < 0.05, "{mean} {var}");
    }
}
