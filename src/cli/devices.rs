//! `flownav devices`: the V4L2 cameras present, with the formats, sizes and frame rates each
//! offers — the values the `[camera]` config table and `--camera` can ask for.

use hal::v4l2::{DeviceInfo, V4l2Error, list_devices};
use std::path::PathBuf;

/// List V4L2 cameras (/dev/video*) with their formats, sizes and frame rates.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {}

/// Prints the listing to stdout; succeeds (exit 0) also when there is no camera.
pub fn run(_args: Args, _common: &super::Common) -> anyhow::Result<()> {
    print!("{}", render(&list_devices()));
    Ok(())
}

/// The listing as text: one block per device node, or a message saying there is none and what
/// to check.
pub fn render(devices: &[(PathBuf, Result<DeviceInfo, V4l2Error>)]) -> String {
    if devices.is_empty() {
        return "No V4L2 cameras found (no /dev/video* devices).\n\
                Plug the camera in and check `dmesg | tail` for a uvcvideo line; \
                inside a container, pass the device through (e.g. `docker run --device /dev/video0`).\n\
                To run without a camera, play a frame folder: `flownav run --camera frames:DIR ...`.\n"
            .into();
    }
    let mut out = String::new();
    for (path, info) in devices {
        match info {
            Ok(info) => out.push_str(&info.to_string()),
            Err(e) => out.push_str(&format!("{}: cannot be queried: {e}\n", path.display())),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn no_camera_gives_a_clear_message() {
        let text = render(&[]);
        assert!(text.starts_with("No V4L2 cameras found"), "{text}");
        assert!(text.contains("frames:DIR"));
    }

    #[test]
    fn unreadable_nodes_are_listed_with_the_reason() {
        let listed =
            vec![(PathBuf::from("/dev/video0"), Err(V4l2Error::PermissionDenied { path: "/dev/video0".into() }))];
        let text = render(&listed);
        assert!(text.contains("/dev/video0: cannot be queried") && text.contains("video` group"), "{text}");
    }
}
