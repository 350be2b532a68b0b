//! [`V4l2Camera`]: opening with strict negotiation, the mmap buffer ring, dequeuing with
//! `poll(2)` and the stall timeout, driver timestamps, and decoding to luma.

use super::config::{CameraConfig, PixelFormat};
use super::error::{V4l2Error, io_error};
use super::probe::{check_supported, describe_device, fmt_fps, fourcc_text, fps_fraction, fps_of, supported_list};
use crate::camera::{Camera, monotonic_ns};
use crate::error::{Error, ErrorKind};
use crate::image::{Frame, LumaImage};
use crate::mjpeg::MjpegDecoder;
use crate::yuyv::yuyv_to_luma;
use std::io;
use std::os::raw::c_void;
use std::path::Path;
use v4l::v4l_sys;
use v4l::{Device, FourCC, Fraction};

/// Number of mmap buffers requested from the driver: enough to absorb a slow frame without the
/// driver dropping one, few enough that a dequeued frame is at most ~3 frame periods old.
const BUFFER_COUNT: u32 = 4;

/// One mmap'ed driver buffer.
struct Mapping {
    ptr: *mut c_void,
    len: usize,
}

/// A V4L2 camera streaming through mmap buffers. Implements [`Camera`]; see the module docs.
pub struct V4l2Camera {
    device: Device,
    cfg: CameraConfig,
    /// Row pitch of YUYV frames (V4L2 `bytesperline`).
    stride: usize,
    buffers: Vec<Mapping>,
    streaming: bool,
    /// Set once the device reported it is gone: every later capture says so again.
    gone: bool,
    decoder: MjpegDecoder,
    /// The MJPEG bytes of the last decoded frame (for logging as captured).
    last_jpeg: Option<std::sync::Arc<[u8]>>,
    seq: u64,
    last_driver_seq: Option<u32>,
    dropped: u64,
    warned_clock: bool,
}

// SAFETY: the raw pointers are private mmap'ed regions owned by this value, only touched through
// `&mut self` and unmapped in `Drop`; moving the owner to another thread is sound.
unsafe impl Send for V4l2Camera {}

fn zeroed_buffer() -> v4l_sys::v4l2_buffer {
    // SAFETY: v4l2_buffer is plain old data; zero is a valid bit pattern.
    let mut buf: v4l_sys::v4l2_buffer = unsafe { std::mem::zeroed() };
    buf.type_ = v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_CAPTURE;
    buf.memory = v4l_sys::v4l2_memory_V4L2_MEMORY_MMAP;
    buf
}

impl V4l2Camera {
    /// Opens `cfg.device`, negotiates exactly `cfg`'s format, size and rate (or fails with an
    /// [`ErrorKind::Unsupported`] error listing what the device offers), maps the buffers and
    /// starts streaming.
    pub fn open(cfg: &CameraConfig) -> Result<Self, V4l2Error> {
        let path = cfg.device.as_path();
        let info = describe_device(path)?;
        if !info.capture {
            return Err(V4l2Error::NotVideoDevice {
                path: path.into(),
                detail: format!(
                    "{} ({}) has no video capture with streaming: a metadata node?",
                    info.card, info.driver
                ),
            });
        }
        let unsupported = |wanted: String, problem: String| V4l2Error::Unsupported {
            path: path.into(),
            wanted,
            problem,
            supported: supported_list(&info.formats),
        };
        check_supported(&info.formats, cfg).map_err(|(w, p)| unsupported(w, p))?;
        let wanted = format!(
            "{} {}x{} at {} fps",
            String::from_utf8_lossy(&cfg.format.fourcc()),
            cfg.width,
            cfg.height,
            fmt_fps(cfg.fps)
        );

        let device = Device::with_path(path).map_err(|e| io_error(path, "open", e))?;
        let (got_fourcc, got_w, got_h, bytesperline) =
            set_format(&device, cfg).map_err(|e| io_error(path, "VIDIOC_S_FMT", e))?;
        if got_fourcc != cfg.format.fourcc() || (got_w, got_h) != (cfg.width, cfg.height) {
            return Err(unsupported(
                wanted,
                format!(
                    "the driver answered with {} {}x{} instead",
                    fourcc_text(FourCC::new(&got_fourcc)),
                    got_w,
                    got_h
                ),
            ));
        }
        let interval = fps_fraction(cfg.fps);
        let got_interval = set_interval(&device, interval).map_err(|e| io_error(path, "VIDIOC_S_PARM", e))?;
        let got_fps = fps_of(got_interval);
        if (got_fps - cfg.fps).abs() > 0.01 * cfg.fps {
            return Err(unsupported(wanted, format!("the driver set {} fps instead", fmt_fps(got_fps))));
        }
        let stride = if bytesperline == 0 { 2 * cfg.width as usize } else { bytesperline as usize };

        let mut cam = Self {
            device,
            cfg: cfg.clone(),
            stride,
            buffers: Vec::new(),
            streaming: false,
            gone: false,
            decoder: MjpegDecoder::with_max_size(cfg.width as usize, cfg.height as usize),
            last_jpeg: None,
            seq: 0,
            last_driver_seq: None,
            dropped: 0,
            warned_clock: false,
        };
        cam.start_streaming()?;
        tracing::info!(
            device = %path.display(),
            card = %info.card,
            "camera streaming {}x{} {} at {} fps",
            cfg.width,
            cfg.height,
            cfg.format.name(),
            fmt_fps(cfg.fps)
        );
        Ok(cam)
    }

    /// The configuration it was opened with.
    pub fn config(&self) -> &CameraConfig {
        &self.cfg
    }

    /// Frames the driver captured but this camera never delivered (gaps in the driver's sequence
    /// numbers: the consumer was slower than the camera and all buffers were full).
    pub fn dropped_frames(&self) -> u64 {
        self.dropped
    }

    fn fd(&self) -> i32 {
        self.device.handle().fd()
    }

    fn path(&self) -> &Path {
        &self.cfg.device
    }

    fn ioctl<T>(&self, op: &'static str, request: v4l::v4l2::vidioc::_IOC_TYPE, arg: &mut T) -> Result<(), V4l2Error> {
        // SAFETY: every caller passes the struct type that `request` reads and writes.
        unsafe { v4l::v4l2::ioctl(self.fd(), request, arg as *mut T as *mut c_void) }
            .map_err(|e| io_error(self.path(), op, e))
    }

    fn start_streaming(&mut self) -> Result<(), V4l2Error> {
        use v4l::v4l2::vidioc;
        // SAFETY: plain old data, zero is valid.
        let mut req: v4l_sys::v4l2_requestbuffers = unsafe { std::mem::zeroed() };
        req.count = BUFFER_COUNT;
        req.type_ = v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_CAPTURE;
        req.memory = v4l_sys::v4l2_memory_V4L2_MEMORY_MMAP;
        self.ioctl("VIDIOC_REQBUFS", vidioc::VIDIOC_REQBUFS, &mut req)?;
        if req.count == 0 {
            return Err(V4l2Error::Io {
                path: self.path().into(),
                op: "VIDIOC_REQBUFS",
                source: io::Error::other("the driver granted no mmap buffers"),
            });
        }
        for index in 0..req.count {
            let mut buf = zeroed_buffer();
            buf.index = index;
            self.ioctl("VIDIOC_QUERYBUF", vidioc::VIDIOC_QUERYBUF, &mut buf)?;
            // SAFETY: the union member `offset` is the one the driver fills for MMAP buffers.
            let offset = unsafe { buf.m.offset };
            let len = buf.length as usize;
            // SAFETY: maps the driver buffer `index` (offset/length from QUERYBUF) read-only.
            let ptr = unsafe {
                v4l::v4l2::mmap(
                    std::ptr::null_mut(),
                    len,
                    libc::PROT_READ,
                    libc::MAP_SHARED,
                    self.fd(),
                    offset as libc::off_t,
                )
            }
            .map_err(|e| io_error(self.path(), "mmap", e))?;
            self.buffers.push(Mapping { ptr, len });
        }
        for index in 0..req.count {
            self.queue(index)?;
        }
        let mut typ = v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_CAPTURE;
        self.ioctl("VIDIOC_STREAMON", vidioc::VIDIOC_STREAMON, &mut typ)?;
        self.streaming = true;
        Ok(())
    }

    fn queue(&self, index: u32) -> Result<(), V4l2Error> {
        let mut buf = zeroed_buffer();
        buf.index = index;
        self.ioctl("VIDIOC_QBUF", v4l::v4l2::vidioc::VIDIOC_QBUF, &mut buf)
    }

    /// Marks the camera gone when `e` says so.
    fn note(&mut self, e: V4l2Error) -> V4l2Error {
        if e.kind() == ErrorKind::Disconnected {
            self.gone = true;
        }
        e
    }

    /// Waits for a filled buffer (at most the stall timeout) and dequeues it.
    fn dequeue(&mut self) -> Result<v4l_sys::v4l2_buffer, V4l2Error> {
        let timeout_ms = self.cfg.stall_timeout_ms;
        let deadline = monotonic_ns() + timeout_ms * 1_000_000;
        loop {
            let now = monotonic_ns();
            if now >= deadline {
                return Err(V4l2Error::Stall { path: self.path().into(), timeout_ms });
            }
            let left_ms = (deadline - now).div_ceil(1_000_000).min(i32::MAX as u64) as i32;
            match self.device.handle().poll(libc::POLLIN, left_ms) {
                Ok(0) => continue,
                Ok(_) => {}
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(self.note(io_error(self.path(), "poll", e))),
            }
            let mut buf = zeroed_buffer();
            // SAFETY: VIDIOC_DQBUF fills one v4l2_buffer.
            let r = unsafe {
                v4l::v4l2::ioctl(self.fd(), v4l::v4l2::vidioc::VIDIOC_DQBUF, &mut buf as *mut _ as *mut c_void)
            };
            match r {
                Ok(()) if (buf.index as usize) < self.buffers.len() => return Ok(buf),
                Ok(()) => {
                    return Err(V4l2Error::Io {
                        path: self.path().into(),
                        op: "VIDIOC_DQBUF",
                        source: io::Error::other(format!("driver returned unknown buffer index {}", buf.index)),
                    });
                }
                Err(e) if matches!(e.kind(), io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted) => continue,
                Err(e) => return Err(self.note(io_error(self.path(), "VIDIOC_DQBUF", e))),
            }
        }
    }

    /// Converts the driver timestamp to ns on the monotonic clock; falls back to the dequeue
    /// time (with one warning) for drivers that do not stamp with `CLOCK_MONOTONIC`.
    fn timestamp_ns(&mut self, buf: &v4l_sys::v4l2_buffer) -> u64 {
        let ts_type = buf.flags & v4l_sys::V4L2_BUF_FLAG_TIMESTAMP_MASK;
        let (sec, usec) = (buf.timestamp.tv_sec, buf.timestamp.tv_usec);
        if ts_type == v4l_sys::V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC && sec >= 0 && usec >= 0 && (sec, usec) != (0, 0) {
            return sec as u64 * 1_000_000_000 + usec as u64 * 1_000;
        }
        if !self.warned_clock {
            self.warned_clock = true;
            tracing::warn!(
                device = %self.path().display(),
                "driver timestamps are not CLOCK_MONOTONIC (flags {:#x}); using dequeue time, latency figures include queueing",
                buf.flags
            );
        }
        monotonic_ns()
    }

    fn decode(&mut self, index: usize, bytesused: usize) -> Result<LumaImage, V4l2Error> {
        let m = &self.buffers[index];
        // SAFETY: the buffer is dequeued (owned by us until re-queued) and `bytesused` is clamped
        // to its mapped length.
        let data = unsafe { std::slice::from_raw_parts(m.ptr as *const u8, bytesused.min(m.len)) };
        let (w, h) = (self.cfg.width as usize, self.cfg.height as usize);
        let mut img = LumaImage::default();
        match self.cfg.format {
            PixelFormat::Mjpeg => {
                self.decoder
                    .decode_into(data, &mut img)
                    .map_err(|source| V4l2Error::Mjpeg { path: self.cfg.device.clone(), source })?;
                self.last_jpeg = Some(std::sync::Arc::from(data));
                if (img.width(), img.height()) != (w, h) {
                    return Err(V4l2Error::FrameSize {
                        path: self.cfg.device.clone(),
                        width: img.width(),
                        height: img.height(),
                        want_width: self.cfg.width,
                        want_height: self.cfg.height,
                    });
                }
            }
            PixelFormat::Yuyv => yuyv_to_luma(data, w, h, self.stride, &mut img)
                .map_err(|source| V4l2Error::Yuyv { path: self.cfg.device.clone(), source })?,
        }
        Ok(img)
    }
}

/// `VIDIOC_S_FMT` for `cfg`'s format and size; returns what the driver set: fourcc, width,
/// height, bytes per line.
fn set_format(dev: &Device, cfg: &CameraConfig) -> io::Result<([u8; 4], u32, u32, u32)> {
    // SAFETY: v4l2_format is plain old data; zero is a valid bit pattern.
    let mut fmt: v4l_sys::v4l2_format = unsafe { std::mem::zeroed() };
    fmt.type_ = v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_CAPTURE;
    // SAFETY: `pix` is the union member for VIDEO_CAPTURE formats.
    unsafe {
        fmt.fmt.pix.width = cfg.width;
        fmt.fmt.pix.height = cfg.height;
        fmt.fmt.pix.pixelformat = u32::from_le_bytes(cfg.format.fourcc());
        fmt.fmt.pix.field = v4l_sys::v4l2_field_V4L2_FIELD_NONE;
        v4l::v4l2::ioctl(dev.handle().fd(), v4l::v4l2::vidioc::VIDIOC_S_FMT, &mut fmt as *mut _ as *mut c_void)?;
        let pix = fmt.fmt.pix;
        Ok((pix.pixelformat.to_le_bytes(), pix.width, pix.height, pix.bytesperline))
    }
}

/// `VIDIOC_S_PARM` with the frame interval; returns the interval the driver set.
fn set_interval(dev: &Device, interval: Fraction) -> io::Result<Fraction> {
    // SAFETY: v4l2_streamparm is plain old data; zero is a valid bit pattern.
    let mut parm: v4l_sys::v4l2_streamparm = unsafe { std::mem::zeroed() };
    parm.type_ = v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_CAPTURE;
    // SAFETY: `capture` is the union member for VIDEO_CAPTURE streams.
    unsafe {
        parm.parm.capture.timeperframe.numerator = interval.numerator;
        parm.parm.capture.timeperframe.denominator = interval.denominator;
        v4l::v4l2::ioctl(dev.handle().fd(), v4l::v4l2::vidioc::VIDIOC_S_PARM, &mut parm as *mut _ as *mut c_void)?;
        let t = parm.parm.capture.timeperframe;
        Ok(Fraction::new(t.numerator, t.denominator))
    }
}

impl Camera for V4l2Camera {
    type Error = V4l2Error;

    /// The next frame, decoded to luma on the calling thread. Errors: `Timeout` after
    /// `stall_timeout_ms` without a frame, `BadData` for a corrupt frame (skipped; its buffer is
    /// returned to the driver), `Disconnected` once the device is gone (reopen it).
    fn capture(&mut self) -> Result<Frame, V4l2Error> {
        if self.gone {
            return Err(V4l2Error::Disconnected {
                path: self.path().into(),
                op: "capture",
                source: io::Error::from_raw_os_error(libc::ENODEV),
            });
        }
        let buf = self.dequeue()?;
        let t_ns = self.timestamp_ns(&buf);
        if let Some(last) = self.last_driver_seq {
            self.dropped += u64::from(buf.sequence.wrapping_sub(last).saturating_sub(1));
        }
        self.last_driver_seq = Some(buf.sequence);
        let result = if buf.flags & v4l_sys::V4L2_BUF_FLAG_ERROR != 0 {
            Err(V4l2Error::CorruptFrame { path: self.path().into(), driver_seq: buf.sequence })
        } else {
            self.decode(buf.index as usize, buf.bytesused as usize)
        };
        // The buffer goes back to the driver whether or not its frame decoded.
        self.queue(buf.index).map_err(|e| self.note(e))?;
        let image = result?;
        let frame = Frame { seq: self.seq, t_ns, image };
        self.seq += 1;
        Ok(frame)
    }

    fn take_encoded(&mut self) -> Option<std::sync::Arc<[u8]>> {
        self.last_jpeg.take()
    }
}

impl Drop for V4l2Camera {
    fn drop(&mut self) {
        // Errors are ignored: the device may be gone, and there is nothing left to do about it.
        if self.streaming {
            let mut typ = v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_CAPTURE;
            let _ = self.ioctl("VIDIOC_STREAMOFF", v4l::v4l2::vidioc::VIDIOC_STREAMOFF, &mut typ);
        }
        for m in self.buffers.drain(..) {
            // SAFETY: each mapping came from a successful mmap of exactly `len` bytes.
            let _ = unsafe { v4l::v4l2::munmap(m.ptr, m.len) };
        }
        // SAFETY: plain old data, zero is valid.
        let mut req: v4l_sys::v4l2_requestbuffers = unsafe { std::mem::zeroed() };
        req.type_ = v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_CAPTURE;
        req.memory = v4l_sys::v4l2_memory_V4L2_MEMORY_MMAP;
        let _ = self.ioctl("VIDIOC_REQBUFS", v4l::v4l2::vidioc::VIDIOC_REQBUFS, &mut req);
    }
}
