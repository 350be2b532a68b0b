//! MJPEG frames → 8-bit luma, with the standard Huffman tables inserted where a UVC camera
//! leaves them out.
//!
//! USB Video Class cameras (the Logitech C310 among them) send Motion-JPEG frames that usually
//! omit the DHT (Define Huffman Table) segment: the MJPEG convention is that a decoder uses the
//! "typical" tables of JPEG Annex K.3 (ITU-T T.81, Tables K.3–K.6). A plain JPEG decoder rejects
//! such a frame ("No DC table for component Y"), so [`MjpegDecoder`] splices [`STANDARD_DHT`] in
//! front of the first SOS marker when no DHT precedes it, then decodes with zune-jpeg.
//!
//! Only luma is produced: zune-jpeg still entropy-decodes the chroma blocks (the bitstream
//! interleaves them) but skips their IDCT, upsampling and colour conversion. Decoding runs in
//! strict mode, so a truncated or corrupt frame is an error ([`crate::ErrorKind::BadData`]),
//! never a half-grey image that would show up as false optical flow.

use crate::error::{Error, ErrorKind};
use crate::image::LumaImage;
use zune_jpeg::JpegDecoder;
use zune_jpeg::zune_core::bytestream::ZCursor;
use zune_jpeg::zune_core::colorspace::ColorSpace;
use zune_jpeg::zune_core::options::DecoderOptions;

/// Why an MJPEG frame could not be decoded. Every variant is [`ErrorKind::BadData`]: skip the
/// frame and take the next one.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum MjpegError {
    #[error("MJPEG frame of {len} bytes does not start with a JPEG SOI marker (FF D8)")]
    NotJpeg { len: usize },
    #[error("MJPEG frame ends at byte {len} before its image data (SOS marker): truncated frame")]
    Truncated { len: usize },
    #[error("MJPEG frame is malformed at byte {offset}: {problem}")]
    Malformed { offset: usize, problem: &'static str },
    #[error("MJPEG frame does not decode: {message}")]
    Decode { message: String },
    #[error("MJPEG frame is {width}x{height}, larger than the {max_width}x{max_height} this decoder accepts")]
    TooLarge { width: usize, height: usize, max_width: usize, max_height: usize },
}

impl Error for MjpegError {
    fn kind(&self) -> ErrorKind {
        ErrorKind::BadData
    }
}

/// Annex K.3 Table K.3: luminance DC code lengths (number of codes of length 1..=16).
const DC_LUMA_BITS: [u8; 16] = [0, 1, 5, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0];
/// Annex K.3 Table K.4: chrominance DC code lengths.
const DC_CHROMA_BITS: [u8; 16] = [0, 3, 1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0];
/// DC symbols (difference categories 0..=11), the same for luma and chroma.
const DC_VALUES: [u8; 12] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11];
/// Annex K.3 Table K.5: luminance AC code lengths.
const AC_LUMA_BITS: [u8; 16] = [0, 2, 1, 3, 3, 2, 4, 3, 5, 5, 4, 4, 0, 0, 1, 0x7d];
/// Annex K.3 Table K.5: luminance AC symbols (run/size), in code order.
#[rustfmt::skip]
const AC_LUMA_VALUES: [u8; 162] = [
    0x01, 0x02, 0x03, 0x00, 0x04, 0x11, 0x05, 0x12, 0x21, 0x31, 0x41, 0x06, 0x13, 0x51, 0x61, 0x07,
    0x22, 0x71, 0x14, 0x32, 0x81, 0x91, 0xa1, 0x08, 0x23, 0x42, 0xb1, 0xc1, 0x15, 0x52, 0xd1, 0xf0,
    0x24, 0x33, 0x62, 0x72, 0x82, 0x09, 0x0a, 0x16, 0x17, 0x18, 0x19, 0x1a, 0x25, 0x26, 0x27, 0x28,
    0x29, 0x2a, 0x34, 0x35, 0x36, 0x37, 0x38, 0x39, 0x3a, 0x43, 0x44, 0x45, 0x46, 0x47, 0x48, 0x49,
    0x4a, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5a, 0x63, 0x64, 0x65, 0x66, 0x67, 0x68, 0x69,
    0x6a, 0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7a, 0x83, 0x84, 0x85, 0x86, 0x87, 0x88, 0x89,
    0x8a, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97, 0x98, 0x99, 0x9a, 0xa2, 0xa3, 0xa4, 0xa5, 0xa6, 0xa7,
    0xa8, 0xa9, 0xaa, 0xb2, 0xb3, 0xb4, 0xb5, 0xb6, 0xb7, 0xb8, 0xb9, 0xba, 0xc2, 0xc3, 0xc4, 0xc5,
    0xc6, 0xc7, 0xc8, 0xc9, 0xca, 0xd2, 0xd3, 0xd4, 0xd5, 0xd6, 0xd7, 0xd8, 0xd9, 0xda, 0xe1, 0xe2,
    0xe3, 0xe4, 0xe5, 0xe6, 0xe7, 0xe8, 0xe9, 0xea, 0xf1, 0xf2, 0xf3, 0xf4, 0xf5, 0xf6, 0xf7, 0xf8,
    0xf9, 0xfa,
];
/// Annex K.3 Table K.6: chrominance AC code lengths.
const AC_CHROMA_BITS: [u8; 16] = [0, 2, 1, 2, 4, 4, 3, 4, 7, 5, 4, 4, 0, 1, 2, 0x77];
/// Annex K.3 Table K.6: chrominance AC symbols, in code order.
#[rustfmt::skip]
const AC_CHROMA_VALUES: [u8; 162] = [
    0x00, 0x01, 0x02, 0x03, 0x11, 0x04, 0x05, 0x21, 0x31, 0x06, 0x12, 0x41, 0x51, 0x07, 0x61, 0x71,
    0x13, 0x22, 0x32, 0x81, 0x08, 0x14, 0x42, 0x91, 0xa1, 0xb1, 0xc1, 0x09, 0x23, 0x33, 0x52, 0xf0,
    0x15, 0x62, 0x72, 0xd1, 0x0a, 0x16, 0x24, 0x34, 0xe1, 0x25, 0xf1, 0x17, 0x18, 0x19, 0x1a, 0x26,
    0x27, 0x28, 0x29, 0x2a, 0x35, 0x36, 0x37, 0x38, 0x39, 0x3a, 0x43, 0x44, 0x45, 0x46, 0x47, 0x48,
    0x49, 0x4a, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5a, 0x63, 0x64, 0x65, 0x66, 0x67, 0x68,
    0x69, 0x6a, 0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7a, 0x82, 0x83, 0x84, 0x85, 0x86, 0x87,
    0x88, 0x89, 0x8a, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97, 0x98, 0x99, 0x9a, 0xa2, 0xa3, 0xa4, 0xa5,
    0xa6, 0xa7, 0xa8, 0xa9, 0xaa, 0xb2, 0xb3, 0xb4, 0xb5, 0xb6, 0xb7, 0xb8, 0xb9, 0xba, 0xc2, 0xc3,
    0xc4, 0xc5, 0xc6, 0xc7, 0xc8, 0xc9, 0xca, 0xd2, 0xd3, 0xd4, 0xd5, 0xd6, 0xd7, 0xd8, 0xd9, 0xda,
    0xe2, 0xe3, 0xe4, 0xe5, 0xe6, 0xe7, 0xe8, 0xe9, 0xea, 0xf2, 0xf3, 0xf4, 0xf5, 0xf6, 0xf7, 0xf8,
    0xf9, 0xfa,
];

/// Length of [`STANDARD_DHT`]: marker (2) + length field (2) + 4 × (class/id + 16 counts) + symbols.
const DHT_SEGMENT_LEN: usize = 4 + 4 * 17 + 12 + 12 + 162 + 162;

/// One DHT segment (marker `FF C4` included) holding the four Annex K.3 tables: DC and AC
/// luminance as table 0, DC and AC chrominance as table 1 — the tables an MJPEG decoder assumes
/// when a frame has none.
pub const STANDARD_DHT: [u8; DHT_SEGMENT_LEN] = build_standard_dht();

const fn build_standard_dht() -> [u8; DHT_SEGMENT_LEN] {
    let mut seg = [0u8; DHT_SEGMENT_LEN];
    let len = (DHT_SEGMENT_LEN - 2) as u16;
    seg[0] = 0xFF;
    seg[1] = 0xC4;
    seg[2] = (len >> 8) as u8;
    seg[3] = len as u8;
    let mut at = 4;
    at = put_table(&mut seg, at, 0x00, &DC_LUMA_BITS, &DC_VALUES);
    at = put_table(&mut seg, at, 0x10, &AC_LUMA_BITS, &AC_LUMA_VALUES);
    at = put_table(&mut seg, at, 0x01, &DC_CHROMA_BITS, &DC_VALUES);
    at = put_table(&mut seg, at, 0x11, &AC_CHROMA_BITS, &AC_CHROMA_VALUES);
    assert!(at == DHT_SEGMENT_LEN);
    seg
}

const fn put_table(
    seg: &mut [u8; DHT_SEGMENT_LEN],
    mut at: usize,
    class_id: u8,
    bits: &[u8; 16],
    values: &[u8],
) -> usize {
    seg[at] = class_id;
    at += 1;
    let mut i = 0;
    while i < 16 {
        seg[at] = bits[i];
        at += 1;
        i += 1;
    }
    i = 0;
    while i < values.len() {
        seg[at] = values[i];
        at += 1;
        i += 1;
    }
    at
}

/// Where the entropy-coded data starts and whether Huffman tables were defined before it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct JpegLayout {
    /// Byte offset of the first SOS marker (`FF DA`).
    pub sos_offset: usize,
    /// Whether a DHT segment precedes the first SOS.
    pub has_dht: bool,
}

/// Walks the marker segments from SOI to the first SOS.
pub fn scan_markers(jpeg: &[u8]) -> Result<JpegLayout, MjpegError> {
    if jpeg.len() < 2 || jpeg[0] != 0xFF || jpeg[1] != 0xD8 {
        return Err(MjpegError::NotJpeg { len: jpeg.len() });
    }
    let truncated = MjpegError::Truncated { len: jpeg.len() };
    let mut has_dht = false;
    let mut i = 2;
    loop {
        match jpeg.get(i) {
            None => return Err(truncated),
            Some(0xFF) => {}
            Some(_) => return Err(MjpegError::Malformed { offset: i, problem: "expected a marker (FF xx)" }),
        }
        // Any number of FF fill bytes may precede a marker code.
        while jpeg.get(i + 1) == Some(&0xFF) {
            i += 1;
        }
        let marker_at = i;
        let Some(&code) = jpeg.get(i + 1) else { return Err(truncated) };
        match code {
            0xDA => return Ok(JpegLayout { sos_offset: marker_at, has_dht }),
            0xD8 | 0xD9 => {
                return Err(MjpegError::Malformed {
                    offset: marker_at,
                    problem: "SOI/EOI marker before the image data",
                });
            }
            0x00 => {
                return Err(MjpegError::Malformed { offset: marker_at, problem: "stuffed byte outside image data" });
            }
            // Standalone markers carry no length field.
            0x01 | 0xD0..=0xD7 => i += 2,
            _ => {
                let (Some(&hi), Some(&lo)) = (jpeg.get(i + 2), jpeg.get(i + 3)) else { return Err(truncated) };
                let seg_len = usize::from(u16::from_be_bytes([hi, lo]));
                if seg_len < 2 {
                    return Err(MjpegError::Malformed { offset: marker_at, problem: "segment length below 2" });
                }
                has_dht |= code == 0xC4;
                i += 2 + seg_len;
            }
        }
    }
}

/// Decodes MJPEG frames to luma, reusing its scratch buffer between frames.
#[derive(Clone, Debug)]
pub struct MjpegDecoder {
    patched: Vec<u8>,
    max_width: usize,
    max_height: usize,
}

impl Default for MjpegDecoder {
    fn default() -> Self {
        Self::new()
    }
}

impl MjpegDecoder {
    /// A decoder accepting frames up to 8192×8192.
    pub fn new() -> Self {
        Self::with_max_size(8192, 8192)
    }

    /// A decoder that rejects frames larger than `max_width`×`max_height` before allocating
    /// anything for them (a corrupt header cannot make it allocate gigabytes).
    pub fn with_max_size(max_width: usize, max_height: usize) -> Self {
        Self { patched: Vec::new(), max_width, max_height }
    }

    /// Decodes one frame into a new luma image.
    pub fn decode(&mut self, jpeg: &[u8]) -> Result<LumaImage, MjpegError> {
        let mut out = LumaImage::default();
        self.decode_into(jpeg, &mut out)?;
        Ok(out)
    }

    /// Decodes one frame into `out`, resizing it to the frame's size (its allocation is reused).
    pub fn decode_into(&mut self, jpeg: &[u8], out: &mut LumaImage) -> Result<(), MjpegError> {
        let layout = scan_markers(jpeg)?;
        let data: &[u8] = if layout.has_dht {
            jpeg
        } else {
            self.patched.clear();
            self.patched.reserve(jpeg.len() + STANDARD_DHT.len());
            self.patched.extend_from_slice(&jpeg[..layout.sos_offset]);
            self.patched.extend_from_slice(&STANDARD_DHT);
            self.patched.extend_from_slice(&jpeg[layout.sos_offset..]);
            &self.patched
        };
        let options = DecoderOptions::default()
            .jpeg_set_out_colorspace(ColorSpace::Luma)
            .set_strict_mode(true)
            .set_max_width(self.max_width)
            .set_max_height(self.max_height);
        let mut decoder = JpegDecoder::new_with_options(ZCursor::new(data), options);
        let decode_err = |e: zune_jpeg::errors::DecodeErrors| MjpegError::Decode { message: e.to_string() };
        decoder.decode_headers().map_err(decode_err)?;
        let (width, height) = decoder.dimensions().ok_or(MjpegError::Truncated { len: jpeg.len() })?;
        if width > self.max_width || height > self.max_height {
            return Err(MjpegError::TooLarge { width, height, max_width: self.max_width, max_height: self.max_height });
        }
        out.resize(width, height);
        decoder.decode_into(out.data_mut()).map_err(decode_err)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn standard_tables_have_consistent_counts() {
        let count = |bits: &[u8; 16]| bits.iter().map(|&b| usize::from(b)).sum::<usize>();
        assert_eq!(count(&DC_LUMA_BITS), DC_VALUES.len());
        assert_eq!(count(&DC_CHROMA_BITS), DC_VALUES.len());
        assert_eq!(count(&AC_LUMA_BITS), AC_LUMA_VALUES.len());
        assert_eq!(count(&AC_CHROMA_BITS), AC_CHROMA_VALUES.len());
        assert_eq!(&STANDARD_DHT[..4], &[0xFF, 0xC4, 0x01, 0xA2], "Annex K segment is 418 bytes long");
    }

    #[test]
    fn marker_walk_finds_sos_and_dht() {
        // SOI, APP0 (len 4), DHT (len 3), SOS.
        let with = [0xFF, 0xD8, 0xFF, 0xE0, 0, 4, 1, 2, 0xFF, 0xC4, 0, 3, 9, 0xFF, 0xFF, 0xDA, 0, 2];
        assert_eq!(scan_markers(&with), Ok(JpegLayout { sos_offset: 14, has_dht: true }));
        let without = [0xFF, 0xD8, 0xFF, 0xDB, 0, 2, 0xFF, 0xDA];
        assert_eq!(scan_markers(&without), Ok(JpegLayout { sos_offset: 6, has_dht: false }));
    }

    #[test]
    fn broken_headers_are_named() {
        assert_eq!(scan_markers(b"GIF89a"), Err(MjpegError::NotJpeg { len: 6 }));
        assert_eq!(scan_markers(&[0xFF, 0xD8, 0xFF, 0xDB, 0, 40]), Err(MjpegError::Truncated { len: 6 }));
        assert!(matches!(scan_markers(&[0xFF, 0xD8, 0x12]), Err(MjpegError::Malformed { offset: 2, .. })));
        assert!(matches!(scan_markers(&[0xFF, 0xD8, 0xFF, 0xC0, 0, 1]), Err(MjpegError::Malformed { .. })));
        let e = MjpegDecoder::new().decode(&[0xFF, 0xD8]).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::BadData);
        assert!(e.to_string().contains("truncated"), "{e}");
    }
}
