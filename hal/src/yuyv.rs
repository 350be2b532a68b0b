//! YUYV (YUV 4:2:2 packed, V4L2 `YUYV`) frames → 8-bit luma.
//!
//! Each pair of pixels is four bytes `Y0 U Y1 V`, so luma is every even byte of a row; rows may
//! be padded (`bytesperline` ≥ 2 × width). No colour conversion is needed: the Y plane is the
//! image flownav works on.

use crate::error::{Error, ErrorKind};
use crate::image::LumaImage;

/// A YUYV buffer that does not hold the frame it claims to. Kind [`ErrorKind::BadData`].
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum YuyvError {
    #[error(
        "YUYV frame of {width}x{height} with {stride} bytes per row needs {needed} bytes, got {got} (short or truncated buffer)"
    )]
    TooShort { width: usize, height: usize, stride: usize, needed: usize, got: usize },
    #[error("YUYV row stride {stride} is below 2 × width {width}")]
    BadStride { width: usize, stride: usize },
}

impl Error for YuyvError {
    fn kind(&self) -> ErrorKind {
        ErrorKind::BadData
    }
}

/// Extracts the Y plane of a YUYV frame into `out` (resized to `width`×`height`, allocation
/// reused). `stride` is the row pitch in bytes (V4L2 `bytesperline`); pass `2 * width` when
/// rows are not padded.
pub fn yuyv_to_luma(
    src: &[u8],
    width: usize,
    height: usize,
    stride: usize,
    out: &mut LumaImage,
) -> Result<(), YuyvError> {
    let row_bytes = 2 * width;
    if stride < row_bytes {
        return Err(YuyvError::BadStride { width, stride });
    }
    let needed = if height == 0 { 0 } else { stride * (height - 1) + row_bytes };
    if src.len() < needed {
        return Err(YuyvError::TooShort { width, height, stride, needed, got: src.len() });
    }
    out.resize(width, height);
    if width == 0 {
        return Ok(());
    }
    for (dst, row) in out.data_mut().chunks_exact_mut(width).zip(src.chunks(stride)) {
        for (d, yuyv) in dst.iter_mut().zip(row[..row_bytes].chunks_exact(2)) {
            *d = yuyv[0];
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn takes_every_even_byte_and_skips_padding() {
        // 4x2 image, stride 10 (2 bytes of padding per row).
        let src = [
            10, 128, 11, 129, 12, 130, 13, 131, 0xEE, 0xEE, //
            20, 128, 21, 129, 22, 130, 23, 131,
        ];
        let mut out = LumaImage::default();
        yuyv_to_luma(&src, 4, 2, 10, &mut out).unwrap();
        assert_eq!(out.data(), &[10, 11, 12, 13, 20, 21, 22, 23]);
    }

    #[test]
    fn short_buffers_and_bad_strides_are_errors() {
        let mut out = LumaImage::default();
        let e = yuyv_to_luma(&[0; 15], 4, 2, 8, &mut out).unwrap_err();
        assert_eq!(e, YuyvError::TooShort { width: 4, height: 2, stride: 8, needed: 16, got: 15 });
        assert_eq!(e.kind(), ErrorKind::BadData);
        assert_eq!(yuyv_to_luma(&[0; 64], 4, 2, 6, &mut out), Err(YuyvError::BadStride { width: 4, stride: 6 }));
    }
}
