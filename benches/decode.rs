//! Camera decode cost at the C310's 1280×720: MJPEG → luma (with the standard Huffman tables
//! inserted, as for a UVC frame) and YUYV → luma. Budget (DESIGN.md): MJPEG ≤ 4 ms per frame.
//!
//! `cargo bench --bench decode` reports two groups: `decode_1280x720` in wall-clock time, and
//! `decode_1280x720_cpu` in the benchmark thread's CPU time (`CLOCK_THREAD_CPUTIME_ID`), which
//! stays meaningful on a loaded shared machine where wall-clock time includes waiting for a core.

use criterion::measurement::{Measurement, ValueFormatter, WallTime};
use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use hal::LumaImage;
use hal::mjpeg::MjpegDecoder;
use hal::yuyv::yuyv_to_luma;
use std::hint::black_box;

const W: u32 = 1280;
const H: u32 = 720;

/// An indoor-like test scene: smooth gradients, edges and fine texture (a pure-noise image would
/// overstate the cost, a flat one understate it).
fn scene() -> Vec<u8> {
    let mut rgb = Vec::with_capacity((W * H * 3) as usize);
    let mut state = 0x2545_f491_u32;
    for y in 0..H {
        for x in 0..W {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            let noise = (state % 9) as i32 - 4;
            let checker = if (x / 40 + y / 40) % 2 == 0 { 50 } else { 0 };
            let ripple = ((x as f32 * 0.11).sin() * (y as f32 * 0.07).cos() * 30.0) as i32;
            let base = (x * 120 / W + y * 80 / H) as i32 + checker + ripple + noise;
            for c in [base + 20, base, base - 25] {
                rgb.push(c.clamp(0, 255) as u8);
            }
        }
    }
    rgb
}

/// The JPEG as a UVC camera sends it: every DHT segment removed. `pixels` is RGB (3 components,
/// 4:4:4) or luma (1 component).
fn uvc_mjpeg(pixels: &[u8], colour: image::ExtendedColorType) -> Vec<u8> {
    let mut jpeg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 85)
        .encode(pixels, W, H, colour)
        .expect("encode test frame");
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

/// CPU time of the calling thread, ns.
fn thread_cpu_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: `ts` is a valid, writable timespec.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    assert_eq!(rc, 0, "CLOCK_THREAD_CPUTIME_ID is available on Linux");
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// Criterion measurement in thread CPU time, formatted like wall-clock time.
struct ThreadCpu {
    wall: WallTime,
}

impl Measurement for ThreadCpu {
    type Intermediate = u64;
    type Value = u64;

    fn start(&self) -> u64 {
        thread_cpu_ns()
    }

    fn end(&self, start: u64) -> u64 {
        thread_cpu_ns() - start
    }

    fn add(&self, a: &u64, b: &u64) -> u64 {
        a + b
    }

    fn zero(&self) -> u64 {
        0
    }

    fn to_f64(&self, v: &u64) -> f64 {
        *v as f64
    }

    fn formatter(&self) -> &dyn ValueFormatter {
        self.wall.formatter()
    }
}

fn bench_wall(c: &mut Criterion) {
    bench(c, "decode_1280x720");
}

fn bench_cpu(c: &mut Criterion<ThreadCpu>) {
    bench(c, "decode_1280x720_cpu");
}

fn bench<M: Measurement>(c: &mut Criterion<M>, name: &str) {
    let rgb = scene();
    let mjpeg = uvc_mjpeg(&rgb, image::ExtendedColorType::Rgb8);
    let grey: Vec<u8> = rgb.chunks_exact(3).map(|p| p[1]).collect();
    let mjpeg_grey = uvc_mjpeg(&grey, image::ExtendedColorType::L8);
    eprintln!(
        "MJPEG test frames: {W}x{H}, quality 85, without DHT: YCbCr 4:4:4 {} bytes, greyscale {} bytes",
        mjpeg.len(),
        mjpeg_grey.len()
    );
    let mut group = c.benchmark_group(name);
    group.throughput(Throughput::Elements(1));

    let mut decoder = MjpegDecoder::new();
    let mut out = LumaImage::default();
    group.bench_function("mjpeg_to_luma", |b| {
        b.iter(|| decoder.decode_into(black_box(&mjpeg), &mut out).expect("decodes"))
    });
    // A one-component frame: the entropy decoding of chroma is gone, so this bounds the cost of a
    // UVC 4:2:2 frame from below, as the 4:4:4 frame bounds it from above.
    group.bench_function("mjpeg_grey_to_luma", |b| {
        b.iter(|| decoder.decode_into(black_box(&mjpeg_grey), &mut out).expect("decodes"))
    });

    let yuyv: Vec<u8> = rgb.chunks_exact(3).flat_map(|p| [p[1], 128]).collect();
    group.bench_function("yuyv_to_luma", |b| {
        b.iter(|| yuyv_to_luma(black_box(&yuyv), W as usize, H as usize, 2 * W as usize, &mut out).expect("fits"))
    });
    group.finish();
}

criterion_group!(wall, bench_wall);
criterion_group! {
    name = cpu;
    config = Criterion::default().with_measurement(ThreadCpu { wall: WallTime });
    targets = bench_cpu
}
criterion_main!(wall, cpu);
