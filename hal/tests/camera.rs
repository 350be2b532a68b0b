//! Camera-side integration tests: MJPEG frames as a UVC camera sends them (no Huffman tables),
//! corrupt and truncated frames, YUYV, and the V4L2 paths that exist without a camera.

use hal::ErrorKind;
use hal::mjpeg::{MjpegDecoder, STANDARD_DHT, scan_markers};
use hal::v4l2::{CameraConfig, V4l2Camera, V4l2Error, list_devices_in};
use hal::yuyv::yuyv_to_luma;
use hal::{Error, LumaImage};
use proptest::prelude::*;

/// A textured colour test scene (gradients, edges, fine detail) and its Rec.601 luma.
fn scene(width: u32, height: u32) -> (Vec<u8>, Vec<u8>) {
    let mut rgb = Vec::with_capacity((width * height * 3) as usize);
    let mut luma = Vec::with_capacity((width * height) as usize);
    for y in 0..height {
        for x in 0..width {
            let checker = if (x / 24 + y / 16) % 2 == 0 { 60 } else { 0 };
            let ripple = ((x as f32 * 0.21).sin() * (y as f32 * 0.17).cos() * 40.0) as i32;
            let r = (x * 200 / width) as i32 + checker + ripple;
            let g = (y * 200 / height) as i32 + ripple;
            let b = 120 + checker - ripple;
            let [r, g, b] = [r, g, b].map(|v| v.clamp(0, 255) as u8);
            rgb.extend([r, g, b]);
            luma.push((0.299 * r as f32 + 0.587 * g as f32 + 0.114 * b as f32).round() as u8);
        }
    }
    (rgb, luma)
}

fn encode_jpeg(rgb: &[u8], width: u32, height: u32, quality: u8) -> Vec<u8> {
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, quality)
        .encode(rgb, width, height, image::ExtendedColorType::Rgb8)
        .unwrap();
    out
}

/// Removes every DHT segment before the scan, as UVC cameras send MJPEG frames.
fn strip_dht(jpeg: &[u8]) -> Vec<u8> {
    let mut out = jpeg[..2].to_vec();
    let mut i = 2;
    while jpeg[i + 1] != 0xDA {
        let len = usize::from(u16::from_be_bytes([jpeg[i + 2], jpeg[i + 3]]));
        if jpeg[i + 1] != 0xC4 {
            out.extend_from_slice(&jpeg[i..i + 2 + len]);
        }
        i += 2 + len;
    }
    out.extend_from_slice(&jpeg[i..]);
    out
}

#[test]
fn uvc_frame_without_huffman_tables_decodes_identically() {
    let (w, h) = (320, 240);
    let (rgb, truth) = scene(w, h);
    let full = encode_jpeg(&rgb, w, h, 85);
    assert!(scan_markers(&full).unwrap().has_dht, "the image crate writes its tables");
    let uvc = strip_dht(&full);
    assert!(!scan_markers(&uvc).unwrap().has_dht);
    assert_eq!(full.len() - uvc.len(), 4 * 4 + STANDARD_DHT.len() - 4, "four DHT segments were removed");

    // Without the inserted tables a plain JPEG decoder rejects the UVC frame.
    let plain = zune_jpeg::JpegDecoder::new(zune_jpeg::zune_core::bytestream::ZCursor::new(&uvc[..])).decode();
    assert!(plain.is_err(), "zune-jpeg decodes a frame without Huffman tables?");

    let mut dec = MjpegDecoder::new();
    let reference = dec.decode(&full).unwrap();
    let patched = dec.decode(&uvc).unwrap();
    assert_eq!((patched.width(), patched.height()), (w as usize, h as usize));
    assert_eq!(patched.data(), reference.data(), "standard tables must decode bit-identically");

    // And the luma is the scene's luma, up to JPEG loss.
    let mad =
        patched.data().iter().zip(&truth).map(|(&a, &b)| (a as f64 - b as f64).abs()).sum::<f64>() / truth.len() as f64;
    assert!(mad < 2.5, "mean absolute luma error {mad:.2} grey levels");
}

#[test]
fn decoder_reuses_its_output_image() {
    let (rgb, _) = scene(64, 48);
    let jpeg = strip_dht(&encode_jpeg(&rgb, 64, 48, 90));
    let mut dec = MjpegDecoder::new();
    let mut img = LumaImage::new(1280, 720);
    dec.decode_into(&jpeg, &mut img).unwrap();
    assert_eq!((img.width(), img.height()), (64, 48));
    let small = MjpegDecoder::with_max_size(32, 32).decode(&jpeg).unwrap_err();
    assert_eq!(small.kind(), ErrorKind::BadData);
}

#[test]
fn truncated_frames_are_bad_data_at_every_length() {
    let (rgb, _) = scene(96, 64);
    let jpeg = strip_dht(&encode_jpeg(&rgb, 96, 64, 85));
    let mut dec = MjpegDecoder::new();
    let sos = scan_markers(&jpeg).unwrap().sos_offset;
    // Cut anywhere up to well into the scan: always an error, never a panic or a grey image.
    for len in (0..jpeg.len() * 3 / 4).step_by(7).chain([sos, sos + 1, jpeg.len() / 2]) {
        match dec.decode(&jpeg[..len]) {
            Err(e) => assert_eq!(e.kind(), ErrorKind::BadData, "{e}"),
            Ok(_) => panic!("a frame cut to {len} of {} bytes decoded", jpeg.len()),
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..2048)) {
        let mut dec = MjpegDecoder::with_max_size(1280, 720);
        if let Err(e) = dec.decode(&bytes) {
            prop_assert_eq!(e.kind(), ErrorKind::BadData);
        }
        let mut with_soi = vec![0xFF, 0xD8];
        with_soi.extend_from_slice(&bytes);
        let _ = dec.decode(&with_soi);
    }

    #[test]
    fn corrupted_frames_never_panic(flips in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8)) {
        let (rgb, _) = scene(48, 32);
        let mut jpeg = strip_dht(&encode_jpeg(&rgb, 48, 32, 80));
        for (at, byte) in flips {
            let i = at.index(jpeg.len());
            jpeg[i] = byte;
        }
        if let Err(e) = MjpegDecoder::with_max_size(1280, 720).decode(&jpeg) {
            prop_assert_eq!(e.kind(), ErrorKind::BadData);
        }
    }
}

#[test]
fn yuyv_luma_is_the_y_plane() {
    let (w, h) = (1280usize, 720usize);
    let (_, luma) = scene(w as u32, h as u32);
    let stride = 2 * w + 64;
    let mut yuyv = vec![0u8; stride * h];
    for y in 0..h {
        for x in 0..w {
            yuyv[y * stride + 2 * x] = luma[y * w + x];
            yuyv[y * stride + 2 * x + 1] = (x * 7 + y * 3) as u8; // chroma: anything
        }
    }
    let mut out = LumaImage::default();
    yuyv_to_luma(&yuyv, w, h, stride, &mut out).unwrap();
    assert_eq!(out.data(), &luma[..]);
    let e = yuyv_to_luma(&yuyv[..stride * (h - 1)], w, h, stride, &mut out).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::BadData);
}

#[test]
fn no_devices_is_an_empty_list() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("not-a-camera"), b"").unwrap();
    assert!(list_devices_in(dir.path()).is_empty());
    assert!(list_devices_in(&dir.path().join("missing")).is_empty());
}

#[test]
fn a_node_that_is_not_v4l2_is_named() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("video3"), b"").unwrap();
    let listed = list_devices_in(dir.path());
    assert_eq!(listed.len(), 1);
    let e = listed[0].1.as_ref().unwrap_err();
    assert!(matches!(e, V4l2Error::NotVideoDevice { .. }), "{e:?}");
    assert!(e.to_string().contains("video3"), "{e}");

    let cfg = CameraConfig { device: "/dev/null".into(), ..CameraConfig::default() };
    let e = V4l2Camera::open(&cfg).err().expect("/dev/null is no camera");
    assert_eq!(e.kind(), ErrorKind::Unsupported, "{e}");
}

#[test]
fn a_missing_camera_names_the_path_and_the_fix() {
    let cfg = CameraConfig { device: "/dev/video_flownav_absent".into(), ..CameraConfig::default() };
    let e = V4l2Camera::open(&cfg).err().expect("no such device");
    assert_eq!(e.kind(), ErrorKind::Disconnected);
    let msg = e.to_string();
    assert!(msg.contains("/dev/video_flownav_absent") && msg.contains("flownav devices"), "{msg}");
}
