//! An FNP/1 base firmware (docs/protocol.md) to port: HELLO/INFO, the watchdog, ODOM at 50 Hz and
//! STATUS at 10 Hz, over the `no_std` `flownav-fnp` crate, running here against a pseudo-terminal
//! that stands in for the UART.
//!
//! ```sh
//! cargo run --example fnp_firmware              # prints the pty path, e.g. /dev/pts/7
//! flownav run --camera frames:DIR --base fnp:/dev/pts/7 --no-log
//! ```
//!
//! `firmware.rs` is the part to port: the main loop's state machine over the [`firmware::Board`]
//! trait, in `core` and `fnp` only. `host.rs` is the stand-in board: the pty, simulated wheels
//! and encoders, the wall clock. `--seconds S` ends the program after S seconds (default: run
//! until interrupted).

mod firmware;
mod host;

use firmware::Params;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// The geometry of flownav's simulated base (`mocks::kinematics::DiffDriveParams`).
const PARAMS: Params = Params { wheel_base_mm: 330, ticks_per_m: 10_000, name: "fnp-firmware" };

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let seconds = match (args.next().as_deref(), args.next()) {
        (None, _) => None,
        (Some("--seconds"), Some(s)) => Some(s.parse::<f64>().map_err(|e| format!("--seconds {s}: {e}"))?),
        _ => return Err("usage: fnp_firmware [--seconds S]".into()),
    };
    let uart = host::PtyUart::open().map_err(|e| format!("cannot open a pseudo-terminal: {e}"))?;
    println!("{}", uart.path().display());
    let stop = Arc::new(AtomicBool::new(false));
    if let Some(s) = seconds {
        let stop = stop.clone();
        let d = Duration::try_from_secs_f64(s).map_err(|e| format!("--seconds {s}: {e}"))?;
        std::thread::spawn(move || {
            std::thread::sleep(d);
            stop.store(true, Ordering::Relaxed);
        });
    }
    host::run(PARAMS, uart, host::Motors::new(), &stop);
    Ok(())
}
