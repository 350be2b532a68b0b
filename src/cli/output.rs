//! What the user sees on stderr: the log lines, progress bars for long commands, and the GPU
//! loaders kept quiet.
//!
//! Output that is not a terminal (a pipe, a file, CI) gets plain text: no ANSI colour codes
//! (also not with `NO_COLOR` set) and no progress bars, so logs read cleanly.

use indicatif::{ProgressBar, ProgressStyle};
use std::io::IsTerminal;

/// Whether stderr is a terminal a person watches.
pub fn stderr_is_terminal() -> bool {
    std::io::stderr().is_terminal()
}

/// Log to stderr; `RUST_LOG` wins over `-v`. Colour only on a terminal.
pub fn init_tracing(verbose: u8) {
    let default = match verbose {
        0 => "info",
        1 => "debug",
        _ => "trace",
    };
    // wgpu's adapter probe logs driver-loading errors on machines without a GPU; they are not
    // ours, and `-v` does not need them either (RUST_LOG=wgpu_hal=debug shows them).
    let default = format!("{default},wgpu_hal=off,wgpu_core=warn,naga=warn");
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(&default));
    let colour = stderr_is_terminal() && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty());
    let _ = tracing_subscriber::fmt().with_env_filter(filter).with_ansi(colour).with_writer(std::io::stderr).try_init();
}

/// Gives the process a private `XDG_RUNTIME_DIR` (`$TMPDIR/flownav-runtime-UID`, mode 0700)
/// when none is set, unless `verbose`.
///
/// The Mesa EGL and Vulkan loaders that wgpu's adapter probe opens print "error:
/// XDG_RUNTIME_DIR is invalid or not set in the environment." straight to stderr when the
/// variable is missing (a service, ssh without a login session, a container). flownav never
/// opens a window, so the directory only has to exist. With `-v` the environment is left as
/// it is and the loaders' messages show.
///
/// # Safety
/// Changes the process environment: call it before any thread is started (first thing in
/// `main`), as [`std::env::set_var`] requires.
pub unsafe fn quiet_gpu_loaders(verbose: u8) {
    if verbose > 0 || std::env::var_os("XDG_RUNTIME_DIR").is_some_and(|d| std::path::Path::new(&d).is_dir()) {
        return;
    }
    use std::os::unix::fs::{DirBuilderExt, MetadataExt, PermissionsExt};
    // The process's own user: the owner of /proc/self (Linux, as V4L2 is).
    let Ok(uid) = std::fs::metadata("/proc/self").map(|m| m.uid()) else { return };
    let dir = std::env::temp_dir().join(format!("flownav-runtime-{uid}"));
    let _ = std::fs::DirBuilder::new().mode(0o700).create(&dir);
    // Use it only when it is ours and closed to others (another user may have made it first).
    let private = std::fs::symlink_metadata(&dir)
        .is_ok_and(|m| m.is_dir() && m.uid() == uid && m.permissions().mode() & 0o077 == 0);
    if private {
        // SAFETY: the caller guarantees no other thread runs yet.
        unsafe { std::env::set_var("XDG_RUNTIME_DIR", &dir) };
    }
}

/// A bar for `len` items of `unit` on stderr: "n of N unit, MESSAGE, ETA"; hidden (draws
/// nothing) when stderr is not a terminal.
pub fn bar(len: u64, unit: &str) -> ProgressBar {
    if !stderr_is_terminal() {
        return ProgressBar::hidden();
    }
    let template = format!("{{pos}} of {{len}} {unit} [{{bar:30}}] {{msg}}, ETA {{eta}}");
    let style = ProgressStyle::with_template(&template).unwrap_or_else(|_| ProgressStyle::default_bar());
    ProgressBar::new(len).with_style(style.progress_chars("=> "))
}

/// A counter for work of unknown length on stderr: "N unit, MESSAGE (elapsed)"; hidden when
/// stderr is not a terminal.
pub fn counter(unit: &str) -> ProgressBar {
    if !stderr_is_terminal() {
        return ProgressBar::hidden();
    }
    let template = format!("{{spinner}} {{pos}} {unit}, {{msg}} ({{elapsed}}, {{per_sec}})");
    let style = ProgressStyle::with_template(&template).unwrap_or_else(|_| ProgressStyle::default_spinner());
    ProgressBar::new_spinner().with_style(style)
}

/// Prints a line on stderr without tearing `bar` (it is redrawn below the line).
pub fn eprintln_above(bar: &ProgressBar, line: &str) {
    bar.suspend(|| eprintln!("{line}"));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bars_are_hidden_off_a_terminal() {
        // Test runs capture stderr or pipe it: no terminal.
        if !stderr_is_terminal() {
            assert!(bar(10, "runs").is_hidden());
            assert!(counter("steps").is_hidden());
        }
    }
}
