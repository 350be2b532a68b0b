//! FNP/1, flownav's serial protocol (docs/protocol.md): the codec and the host's unit conversions.
//!
//! The codec (frames, packets, CRC-16, COBS, the incremental [`Decoder`]) is the `no_std`
//! `flownav-fnp` crate, re-exported here whole, so firmware and host share one implementation.
//! What only a host needs is added here: conversions between SI units (f64) and the protocol's
//! integer fields, strict for commands ([`setpoint_fields`]) and saturating for measurements
//! ([`to_i16_clamped`]).

pub use ::fnp::*;

/// A set-point in SI units that does not fit FNP/1's 16-bit SETPOINT fields.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
#[error(
    "{what} set-point {value} {unit} does not fit FNP/1's ±{limit:.3} {unit} field \
     (the [control] limits clamp set-points before they reach the driver)"
)]
pub struct OutOfRange {
    /// "linear" or "angular".
    pub what: &'static str,
    pub value: f64,
    pub unit: &'static str,
    pub limit: f64,
}

/// `value` (SI units) in the protocol's units (`scale` per SI unit), rounded, if it fits an i16.
pub fn to_i16_checked(value: f64, scale: f64) -> Option<i16> {
    let x = (value * scale).round();
    // NaN is in no range.
    (f64::from(i16::MIN)..=f64::from(i16::MAX)).contains(&x).then_some(x as i16)
}

/// SETPOINT's fields `(v_mm_s, omega_mrad_s)` for a body velocity in m/s and rad/s; an error
/// names a value that does not fit.
///
/// The driver refuses such a command rather than saturating it: a set-point beyond ±32.767 m/s
/// or ±32.767 rad/s is a fault upstream, and sending 32.767 m/s for 100 m/s would hide it.
pub fn setpoint_fields(v_m_s: f64, omega_rad_s: f64) -> Result<(i16, i16), OutOfRange> {
    let limit = f64::from(i16::MAX) / 1000.0;
    let v_mm_s =
        to_i16_checked(v_m_s, 1000.0).ok_or(OutOfRange { what: "linear", value: v_m_s, unit: "m/s", limit })?;
    let omega_mrad_s = to_i16_checked(omega_rad_s, 1000.0).ok_or(OutOfRange {
        what: "angular",
        value: omega_rad_s,
        unit: "rad/s",
        limit,
    })?;
    Ok((v_mm_s, omega_mrad_s))
}

/// Saturating conversion of a value in SI units to a protocol integer (`scale` = units per SI
/// unit); NaN gives 0. For measurements a base reports (a wheel spinning faster than the field
/// holds reports the field's limit) and for modelling what a base holds; commands go through
/// [`setpoint_fields`], which refuses what does not fit.
pub fn to_i16_clamped(value: f64, scale: f64) -> i16 {
    let x = (value * scale).round();
    if x.is_nan() { 0 } else { x.clamp(f64::from(i16::MIN), f64::from(i16::MAX)) as i16 }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn setpoints_that_fit_are_rounded_to_mm_and_mrad() {
        assert_eq!(setpoint_fields(0.3, -0.15), Ok((300, -150)));
        assert_eq!(setpoint_fields(32.767, -32.768), Ok((i16::MAX, i16::MIN)));
        assert_eq!(setpoint_fields(0.00049, 0.0), Ok((0, 0)));
    }

    #[test]
    fn setpoints_that_do_not_fit_are_errors_naming_the_value() {
        let e = setpoint_fields(100.0, 0.0).unwrap_err();
        assert_eq!((e.what, e.value), ("linear", 100.0));
        assert!(e.to_string().starts_with("linear set-point 100 m/s does not fit FNP/1's ±32.767 m/s field"), "{e}");
        let e = setpoint_fields(0.2, -40.0).unwrap_err();
        assert!(
            e.to_string().starts_with("angular set-point -40 rad/s does not fit FNP/1's ±32.767 rad/s field"),
            "{e}"
        );
        // Just past the edge (32768 mm/s; -32768 fits), and NaN.
        assert_eq!(setpoint_fields(32.768, 0.0).unwrap_err().value, 32.768);
        assert!(setpoint_fields(0.0, -32.769).is_err());
        assert!(setpoint_fields(f64::NAN, 0.0).unwrap_err().to_string().starts_with("linear set-point NaN m/s"));
        assert!(setpoint_fields(0.0, f64::INFINITY).is_err());
    }

    #[test]
    fn measurements_saturate() {
        assert_eq!(to_i16_clamped(0.3, 1000.0), 300);
        assert_eq!(to_i16_clamped(100.0, 1000.0), i16::MAX);
        assert_eq!(to_i16_clamped(-100.0, 1000.0), i16::MIN);
        assert_eq!(to_i16_clamped(f64::NAN, 1000.0), 0);
    }
}
