//! `flownav calib`: camera calibrations.
//!
//! - `flownav calib import FILE [--mount X,Y,Z,PITCH] [-o calib/NAME.toml]`: an OpenCV
//!   (`cv::FileStorage` YAML or XML) or ROS `camera_info` YAML calibration → flownav's TOML.
//! - `flownav calib show [FILE]`: intrinsics, field of view and the distortion at the corners of
//!   a calibration (flownav TOML, or a file `import` reads); without FILE, the one in effect
//!   (`--calib`, else the built-in nominal C310).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::{Args as ClapArgs, Subcommand};
use hal::Calibration;
use hal::calib::Mount;

use super::Common;
use crate::calib_import::{self, Imported};

#[derive(Debug, ClapArgs)]
pub struct Args {
    #[command(subcommand)]
    pub command: CalibCommand,
}

#[derive(Debug, Subcommand)]
pub enum CalibCommand {
    /// Convert an OpenCV (YAML/XML) or ROS camera_info (YAML) calibration to flownav's TOML.
    Import {
        /// The calibration file (OpenCV calibrateCamera output saved with cv::FileStorage, or
        /// what ROS camera_calibration writes).
        file: PathBuf,
        /// Where the camera sits: ahead of the axle midpoint, left of it, height above the floor
        /// (m), downward tilt (rad). Default: the nominal C310 mount (0.10,0,0.40,0).
        #[arg(long, value_name = "X,Y,Z,PITCH", value_parser = parse_mount, allow_hyphen_values = true)]
        mount: Option<Mount>,
        /// Write the TOML here (e.g. calib/mycam.toml) instead of to stdout.
        #[arg(short, long, value_name = "FILE")]
        output: Option<PathBuf>,
        /// Overwrite the output file if it exists.
        #[arg(long)]
        force: bool,
    },
    /// Print a calibration's intrinsics, field of view and distortion at the image corners.
    Show {
        /// flownav TOML, or an OpenCV/ROS file as `import` reads; default: the calibration in
        /// effect (--calib, else the built-in nominal C310).
        file: Option<PathBuf>,
    },
}

pub fn run(args: Args, common: &Common) -> anyhow::Result<()> {
    match args.command {
        CalibCommand::Import { file, mount, output, force } => import(&file, mount, output.as_deref(), force),
        CalibCommand::Show { file } => {
            let (origin, calib, has_mount) = match file {
                Some(path) => load_any(&path)?,
                None => match &common.calib {
                    Some(path) => load_any(path)?,
                    None => ("built-in".to_string(), Calibration::nominal_c310(), true),
                },
            };
            print!("{}", describe(&origin, &calib, has_mount));
            Ok(())
        }
    }
}

/// `--mount X,Y,Z,PITCH`: four numbers, metres and radians.
fn parse_mount(s: &str) -> Result<Mount, String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let numbers: Option<Vec<f64>> = parts.iter().map(|p| p.parse::<f64>().ok().filter(|v| v.is_finite())).collect();
    match numbers.as_deref() {
        Some(&[x_m, y_m, z_m, pitch_rad]) => Ok(Mount { x_m, y_m, z_m, pitch_rad }),
        _ => Err(format!(
            "--mount {s:?}: expected four numbers X,Y,Z,PITCH (metres ahead, left, above the floor; \
             downward tilt in radians), e.g. 0.10,0,0.40,0.05"
        )),
    }
}

fn read(path: &Path) -> anyhow::Result<String> {
    std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))
}

fn is_flownav_toml(path: &Path) -> bool {
    path.extension().is_some_and(|e| e.eq_ignore_ascii_case("toml"))
}

/// A flownav TOML (with its mount), or an imported OpenCV/ROS file (intrinsics only).
fn load_any(path: &Path) -> anyhow::Result<(String, Calibration, bool)> {
    let origin = path.display().to_string();
    if is_flownav_toml(path) {
        return Ok((origin, Calibration::load(path)?, true));
    }
    let imported = calib_import::import(&read(path)?, &origin)?;
    let calib = calibration(&imported, &origin, Calibration::nominal_c310().mount)
        .with_context(|| format!("{origin} is not a usable calibration"))?;
    Ok((format!("{origin} ({})", imported.format), calib, false))
}

/// The flownav calibration of an imported file, validated as `--calib` would.
fn calibration(imported: &Imported, origin: &str, mount: Mount) -> anyhow::Result<Calibration> {
    let stem = Path::new(origin).file_stem().map(|s| s.to_string_lossy().into_owned());
    let name = imported.camera_name.clone().or(stem).unwrap_or_else(|| "camera".into());
    let calib = Calibration {
        model: format!("{name} (imported from the {} file {origin})", imported.format),
        camera: imported.camera,
        mount,
    };
    // The same checks as loading the file later (a lens model over the image, a sane mount).
    Calibration::from_toml(&calib.to_toml(""), origin)?;
    Ok(calib)
}

fn import(file: &Path, mount: Option<Mount>, output: Option<&Path>, force: bool) -> anyhow::Result<()> {
    let origin = file.display().to_string();
    if is_flownav_toml(file) {
        bail!("{origin} is already a flownav calibration: use it with --calib {origin}");
    }
    let imported = calib_import::import(&read(file)?, &origin)?;
    let calib = calibration(&imported, &origin, mount.unwrap_or(Calibration::nominal_c310().mount))?;
    let mut header = format!("# Imported by `flownav calib import` from {origin} ({}).\n", imported.format);
    if mount.is_none() {
        header.push_str(
            "# The [mount] is the nominal C310 mount, not this robot's: measure it and edit below\n\
             # (or import again with --mount X,Y,Z,PITCH).\n",
        );
    }
    let text = calib.to_toml(&header);
    // What is written must read back as the same numbers.
    let back = Calibration::from_toml(&text, &origin)?;
    if back != calib {
        bail!("internal error: the TOML written for {origin} does not read back the same");
    }
    match output {
        None => print!("{text}"),
        Some(out) => {
            if out.exists() && !force {
                bail!("{} exists; pass --force to overwrite it", out.display());
            }
            std::fs::write(out, &text).with_context(|| format!("cannot write {}", out.display()))?;
            eprint!("{}", describe(&out.display().to_string(), &calib, mount.is_some()));
            eprintln!("wrote {}; use it with --calib {}", out.display(), out.display());
        }
    }
    if mount.is_none() {
        tracing::warn!("no --mount given: the file has the nominal C310 mount; measure yours and edit [mount]");
    }
    Ok(())
}

/// What `calib show` prints.
pub fn describe(origin: &str, calib: &Calibration, has_mount: bool) -> String {
    let c = &calib.camera;
    let [k1, k2, p1, p2, k3] = c.distortion;
    let mut out = String::new();
    let _ = writeln!(out, "calibration   {origin}");
    if !calib.model.is_empty() {
        let _ = writeln!(out, "model         {}", calib.model);
    }
    let _ = writeln!(out, "image         {} x {} px", c.width, c.height);
    let _ = writeln!(out, "focal length  fx {} px, fy {} px", c.fx, c.fy);
    let _ = writeln!(out, "principal pt  cx {} px, cy {} px", c.cx, c.cy);
    let _ = writeln!(out, "distortion    k1 {k1}, k2 {k2}, p1 {p1}, p2 {p2}, k3 {k3} (plumb_bob)");
    match calib.field_of_view() {
        Some(f) => {
            let _ = writeln!(
                out,
                "field of view {:.2}° horizontal, {:.2}° vertical, {:.2}° diagonal",
                f.horizontal_rad.to_degrees(),
                f.vertical_rad.to_degrees(),
                f.diagonal_rad.to_degrees()
            );
        }
        None => _ = writeln!(out, "field of view (the lens model cannot be inverted at the image edges)"),
    }
    if let Some(corners) = calib.corner_displacements_px() {
        let _ = writeln!(out, "distortion at the corners (corner minus its ideal pinhole position, px):");
        for (name, [dx, dy]) in ["top-left", "top-right", "bottom-left", "bottom-right"].iter().zip(corners) {
            let _ = writeln!(out, "  {name:<13} {:6.2} px  ({dx:+.2}, {dy:+.2})", dx.hypot(dy));
        }
    }
    let m = &calib.mount;
    if has_mount {
        let _ = writeln!(
            out,
            "mount         x {} m ahead, y {} m left, z {} m up, pitch {} rad ({:.2}° down)",
            m.x_m,
            m.y_m,
            m.z_m,
            m.pitch_rad,
            m.pitch_rad.to_degrees()
        );
    } else {
        let _ = writeln!(out, "mount         (not in this file: `calib import --mount` adds it)");
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mount_takes_four_numbers() {
        let m = parse_mount("0.12, -0.02,0.35,0.1").unwrap();
        assert_eq!(m, Mount { x_m: 0.12, y_m: -0.02, z_m: 0.35, pitch_rad: 0.1 });
        for bad in ["0.1,0,0.4", "0.1,0,0.4,0,1", "a,0,0.4,0", "0.1,0,inf,0"] {
            assert!(parse_mount(bad).unwrap_err().contains("X,Y,Z,PITCH"), "{bad}");
        }
    }
}
