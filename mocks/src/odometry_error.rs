//! How a simulated base's dead reckoning departs from its true motion.
//!
//! The firmware turns a body set-point into wheel speeds with its *nominal* wheel radius and wheel
//! base, and reports odometry from its encoder ticks with the same nominal figures. The wheels it
//! actually has differ:
//!
//! - `left`, `right`: the true radius of each wheel differs from the nominal one by this fraction,
//!   so the ground covered per tick does too (a worn or under-inflated tyre);
//! - `wheelbase`: the true distance between the wheels' contact points differs by this fraction;
//! - `noise`: each encoder increment carries relative noise of this standard deviation;
//! - `slip`: this fraction of the turn the wheels make is lost on the floor while turning.
//!
//! With a wheel speed `u` (what the ticks say) the ground speed is `u·(1 + e)`, the body turns at
//! `(u_r·(1 + right) − u_l·(1 + left)) / (b·(1 + wheelbase)) · (1 − slip)`, and the odometry keeps
//! reporting `u` with the nominal `b`. A straight command therefore drives an arc of curvature
//! `(right − left) / (b·(1 + wheelbase))` (for small errors) while the odometry says "straight".
//!
//! The spec is `left=F,right=F,wheelbase=F,noise=F,slip=F`, any subset, or `none` for the ideal
//! base. [`OdometryError::UNCALIBRATED`] is the default of `flownav sim`.

use std::fmt;
use std::str::FromStr;

/// Departures of a simulated base's true wheels from its firmware's nominal ones (module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OdometryError {
    /// True left wheel radius relative to nominal, minus 1.
    pub left: f64,
    /// True right wheel radius relative to nominal, minus 1.
    pub right: f64,
    /// True wheel base relative to nominal, minus 1.
    pub wheelbase: f64,
    /// Relative standard deviation of each encoder increment.
    pub noise: f64,
    /// Fraction of the wheels' turn lost to slip.
    pub slip: f64,
}

impl OdometryError {
    /// The ideal base: odometry equals the true motion.
    pub const NONE: Self = Self { left: 0.0, right: 0.0, wheelbase: 0.0, noise: 0.0, slip: 0.0 };

    /// A plausible base that nobody has calibrated. Borenstein and Feng's UMBmark runs found an
    /// uncalibrated research base's wheel diameters 0.4 % apart and its effective wheel base a
    /// few percent off its drawing; rubber tyres on a smooth floor lose a few percent of a turn;
    /// and the quadrature encoders' quantisation and jitter are about 1 % per increment at the
    /// rates a 20 ms odometry period sees. So: the left wheel 0.2 % large and the right one
    /// 0.2 % small (the base drifts clockwise by ~0.7°/m), the wheel base 2 % wide (turns come
    /// out 2 % short), 1 % encoder noise, 2 % slip in turns.
    pub const UNCALIBRATED: Self = Self { left: 0.002, right: -0.002, wheelbase: 0.02, noise: 0.01, slip: 0.02 };

    /// The keys of the spec, in order.
    pub const KEYS: [&'static str; 5] = ["left", "right", "wheelbase", "noise", "slip"];

    fn field(&mut self, key: &str) -> Option<&mut f64> {
        Some(match key {
            "left" => &mut self.left,
            "right" => &mut self.right,
            "wheelbase" => &mut self.wheelbase,
            "noise" => &mut self.noise,
            "slip" => &mut self.slip,
            _ => return None,
        })
    }

    /// Checks each value's range, naming the key that is out of it.
    pub fn validate(&self) -> Result<(), OdometryErrorSpecError> {
        let check = |key: &'static str, value: f64, lo: f64, hi: f64| {
            if value.is_finite() && (lo..=hi).contains(&value) {
                Ok(())
            } else {
                Err(OdometryErrorSpecError::OutOfRange { key, value, range: (lo, hi) })
            }
        };
        check("left", self.left, -0.5, 0.5)?;
        check("right", self.right, -0.5, 0.5)?;
        check("wheelbase", self.wheelbase, -0.5, 0.5)?;
        check("noise", self.noise, 0.0, 0.5)?;
        check("slip", self.slip, 0.0, 0.9)
    }

    /// True body velocity for wheel speeds `(u_l, u_r)` (m/s, as the ticks count them) on a base
    /// whose nominal wheel base is `wheel_base_m`.
    pub fn true_body_velocity(&self, u_l: f64, u_r: f64, wheel_base_m: f64) -> (f64, f64) {
        let (g_l, g_r) = (u_l * (1.0 + self.left), u_r * (1.0 + self.right));
        let v = 0.5 * (g_l + g_r);
        let omega = (g_r - g_l) / (wheel_base_m * (1.0 + self.wheelbase)) * (1.0 - self.slip);
        (v, omega)
    }
}

impl fmt::Display for OdometryError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if *self == Self::NONE {
            return f.write_str("none");
        }
        write!(
            f,
            "left={},right={},wheelbase={},noise={},slip={}",
            self.left, self.right, self.wheelbase, self.noise, self.slip
        )
    }
}

/// A bad `--odometry-error` spec.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum OdometryErrorSpecError {
    #[error("odometry error spec: unknown key {key:?}; the keys are left, right, wheelbase, noise, slip (or `none`)")]
    UnknownKey { key: String },
    #[error("odometry error spec: {key:?} has no value; write {key}=F, e.g. {key}=0.01")]
    MissingValue { key: String },
    #[error("odometry error spec: {key}={value:?} is not a number; write a fraction, e.g. {key}=0.01 for 1 %")]
    NotANumber { key: String, value: String },
    #[error("odometry error spec: {key:?} is given twice")]
    Repeated { key: String },
    #[error("odometry error spec: {key}={value} is outside {}..={}", range.0, range.1)]
    OutOfRange { key: &'static str, value: f64, range: (f64, f64) },
}

impl FromStr for OdometryError {
    type Err = OdometryErrorSpecError;

    /// `left=F,right=F,wheelbase=F,noise=F,slip=F`, any subset (the others are 0), or `none`.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let s = s.trim();
        let mut spec = Self::NONE;
        if s.eq_ignore_ascii_case("none") || s.is_empty() {
            return Ok(spec);
        }
        let mut seen = Vec::new();
        for (key, value) in crate::spec::items(s) {
            let value = value.unwrap_or("");
            let known = spec.field(key).is_some();
            if !known {
                return Err(OdometryErrorSpecError::UnknownKey { key: key.to_string() });
            }
            if value.is_empty() {
                return Err(OdometryErrorSpecError::MissingValue { key: key.to_string() });
            }
            if seen.contains(&key) {
                return Err(OdometryErrorSpecError::Repeated { key: key.to_string() });
            }
            seen.push(key);
            let parsed: f64 = value
                .parse()
                .map_err(|_| OdometryErrorSpecError::NotANumber { key: key.to_string(), value: value.to_string() })?;
            if let Some(slot) = spec.field(key) {
                *slot = parsed;
            }
        }
        spec.validate()?;
        Ok(spec)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_subsets_and_none() {
        assert_eq!("none".parse::<OdometryError>().unwrap(), OdometryError::NONE);
        let e: OdometryError = "left=0.01, slip=0.05".parse().unwrap();
        assert_eq!(e, OdometryError { left: 0.01, slip: 0.05, ..OdometryError::NONE });
        let all: OdometryError = "left=-0.02,right=0.03,wheelbase=0.01,noise=0.02,slip=0.1".parse().unwrap();
        assert_eq!(all, OdometryError { left: -0.02, right: 0.03, wheelbase: 0.01, noise: 0.02, slip: 0.1 });
        // Display round-trips.
        assert_eq!(all.to_string().parse::<OdometryError>().unwrap(), all);
        assert_eq!(
            OdometryError::UNCALIBRATED.to_string().parse::<OdometryError>().unwrap(),
            OdometryError::UNCALIBRATED
        );
    }

    #[test]
    fn bad_specs_name_the_key() {
        let err = |s: &str| s.parse::<OdometryError>().unwrap_err().to_string();
        assert!(err("lefty=0.1").contains("\"lefty\""), "{}", err("lefty=0.1"));
        assert!(err("left").contains("\"left\" has no value"));
        assert!(err("right=abc").contains("right=\"abc\" is not a number"));
        assert!(err("noise=-0.1").contains("noise=-0.1 is outside"));
        assert!(err("slip=0.1,slip=0.2").contains("\"slip\" is given twice"));
        assert!(err("wheelbase=NaN").contains("wheelbase=NaN"));
    }

    #[test]
    fn wheel_radius_errors_bend_a_straight_command() {
        let e = OdometryError { left: -0.01, right: 0.01, ..OdometryError::NONE };
        // Both wheels commanded 0.5 m/s: the right covers 0.505, the left 0.495 m/s.
        let (v, w) = e.true_body_velocity(0.5, 0.5, 0.25);
        assert!((v - 0.5).abs() < 1e-12);
        assert!((w - 0.01 / 0.25).abs() < 1e-12, "{w}");
        let slipping = OdometryError { wheelbase: 0.25, slip: 0.2, ..OdometryError::NONE };
        let (_, w) = slipping.true_body_velocity(-0.1, 0.1, 0.25);
        assert!((w - 0.2 / 0.3125 * 0.8).abs() < 1e-12, "{w}");
    }
}
