//! Image files checked before any decoder sees them. OpenCV decodes a truncated JPEG or PNG
//! partially and fills the rest without an error, and picks its decoder by content, so that a
//! malformed file of another format (its DICOM reader asserts) can abort the process: only
//! JPEG and PNG files whose structure is whole reach it.

use std::path::Path;

use opencv::core::{Mat, Vector};
use opencv::prelude::*;

use crate::error::{MatchingError, Result};

/// Why an image file cannot be used, found from its bytes alone (no decoding): empty, not a
/// JPEG or PNG (other formats never reach OpenCV, some of whose readers abort on malformed
/// files), or a JPEG/PNG whose structure is broken (truncated, a segment or chunk that
/// runs past the end, a PNG chunk whose CRC does not match). OpenCV decodes such files
/// partially and fills the rest without an error, so this runs first.
pub fn image_problem(bytes: &[u8]) -> Option<String> {
    const PNG: &[u8] = b"\x89PNG\r\n\x1a\n";
    if bytes.is_empty() {
        return Some("empty file".into());
    }
    if bytes.starts_with(&[0xFF, 0xD8, 0xFF]) {
        return jpeg_problem(bytes);
    }
    if bytes.starts_with(PNG) {
        return png_problem(&bytes[PNG.len()..], PNG.len());
    }
    Some("not a JPEG or PNG image (posediff reads JPEG and PNG files)".into())
}

fn jpeg_problem(b: &[u8]) -> Option<String> {
    let mut at = 2;
    let mut frame = false;
    loop {
        // A marker: 0xFF (fill bytes allowed), then its code.
        if at >= b.len() {
            return Some(format!(
                "truncated JPEG: ends at byte {at} without an end-of-image marker"
            ));
        }
        if b[at] != 0xFF {
            return Some(format!("corrupt JPEG: no marker at byte {at}"));
        }
        while at < b.len() && b[at] == 0xFF {
            at += 1;
        }
        let Some(&code) = b.get(at) else {
            return Some("truncated JPEG: ends inside a marker".into());
        };
        at += 1;
        match code {
            0xD9 => {
                return (!frame)
                    .then(|| "corrupt JPEG: no frame header (SOF) before the end".into());
            }
            0x01 | 0xD0..=0xD7 => continue,
            _ => {}
        }
        let Some(len) = b
            .get(at..at + 2)
            .map(|l| usize::from(u16::from_be_bytes([l[0], l[1]])))
        else {
            return Some(format!(
                "truncated JPEG: segment 0x{code:02X} header at byte {at}"
            ));
        };
        if len < 2 || at + len > b.len() {
            return Some(format!(
                "truncated JPEG: segment 0x{code:02X} at byte {at} runs past the end of the file"
            ));
        }
        if matches!(code, 0xC0..=0xCF) && !matches!(code, 0xC4 | 0xC8 | 0xCC) {
            frame = true;
        }
        at += len;
        if code == 0xDA {
            // Entropy-coded data: up to the next marker that is not a stuffed 0xFF00 or a
            // restart marker.
            loop {
                match b.get(at) {
                    None => {
                        return Some(
                            "truncated JPEG: the image data ends without an end-of-image marker"
                                .into(),
                        );
                    }
                    Some(0xFF) => match b.get(at + 1) {
                        Some(0x00 | 0xD0..=0xD7 | 0xFF) => at += 1,
                        Some(_) => break,
                        None => {
                            return Some(
                                "truncated JPEG: the image data ends without an end-of-image marker"
                                    .into(),
                            );
                        }
                    },
                    Some(_) => at += 1,
                }
            }
        }
    }
}

fn png_problem(b: &[u8], offset: usize) -> Option<String> {
    let mut at = 0;
    let mut first = true;
    loop {
        let Some(head) = b.get(at..at + 8) else {
            return Some(format!(
                "truncated PNG: ends at byte {} without an IEND chunk",
                offset + at
            ));
        };
        let len = u32::from_be_bytes([head[0], head[1], head[2], head[3]]) as usize;
        let kind = &head[4..8];
        let name = String::from_utf8_lossy(kind).into_owned();
        if first && kind != b"IHDR" {
            return Some("corrupt PNG: the first chunk is not IHDR".into());
        }
        first = false;
        let Some(end) = (at + 8).checked_add(len).filter(|e| e + 4 <= b.len()) else {
            return Some(format!(
                "truncated PNG: chunk {name} at byte {} runs past the end of the file",
                offset + at
            ));
        };
        let stored = u32::from_be_bytes([b[end], b[end + 1], b[end + 2], b[end + 3]]);
        let mut crc = crc32fast::Hasher::new();
        crc.update(&b[at + 4..end]);
        if crc.finalize() != stored {
            return Some(format!(
                "corrupt PNG: chunk {name} at byte {} fails its CRC",
                offset + at
            ));
        }
        if kind == b"IEND" {
            return None;
        }
        at = end + 4;
    }
}

/// The `(width, height)` a JPEG's frame header or a PNG's IHDR states, from the bytes alone
/// (before any EXIF orientation); `None` for anything else or a header that is not whole.
pub fn header_size(b: &[u8]) -> Option<(u32, u32)> {
    if b.starts_with(b"\x89PNG\r\n\x1a\n") && b.get(12..16) == Some(b"IHDR") {
        let be = |at: usize| Some(u32::from_be_bytes(b.get(at..at + 4)?.try_into().ok()?));
        return Some((be(16)?, be(20)?));
    }
    if !b.starts_with(&[0xFF, 0xD8]) {
        return None;
    }
    let mut at = 2;
    loop {
        while *b.get(at)? == 0xFF {
            at += 1;
        }
        let code = *b.get(at)?;
        at += 1;
        if matches!(code, 0x01 | 0xD0..=0xD7) {
            continue;
        }
        if matches!(code, 0xD9 | 0xDA) {
            return None;
        }
        let len = usize::from(u16::from_be_bytes([*b.get(at)?, *b.get(at + 1)?]));
        if matches!(code, 0xC0..=0xCF) && !matches!(code, 0xC4 | 0xC8 | 0xCC) {
            let h = u16::from_be_bytes([*b.get(at + 3)?, *b.get(at + 4)?]);
            let w = u16::from_be_bytes([*b.get(at + 5)?, *b.get(at + 6)?]);
            return Some((u32::from(w), u32::from(h)));
        }
        at += len;
    }
}

/// [`header_size`] of the file at `path`, from its first MiB (the whole file only when the
/// frame header lies beyond it).
///
/// # Errors
/// The file cannot be read.
pub fn header_size_of(path: &Path) -> std::io::Result<Option<(u32, u32)>> {
    use std::io::Read;
    let mut head = Vec::new();
    std::fs::File::open(path)?
        .take(1 << 20)
        .read_to_end(&mut head)?;
    match header_size(&head) {
        Some(size) => Ok(Some(size)),
        None => Ok(header_size(&std::fs::read(path)?)),
    }
}

/// Whether the file starts like a JPEG or a PNG.
pub fn is_jpeg_or_png(path: &Path) -> bool {
    use std::io::Read;
    let mut head = [0u8; 8];
    std::fs::File::open(path)
        .and_then(|mut f| f.read_exact(&mut head))
        .is_ok()
        && (head.starts_with(&[0xFF, 0xD8, 0xFF]) || head == *b"\x89PNG\r\n\x1a\n")
}

/// Reads `path`, checks its structure ([`image_problem`]) and decodes it with OpenCV
/// (`flags`: `IMREAD_COLOR`, `IMREAD_GRAYSCALE`).
///
/// # Errors
/// [`MatchingError::UnreadableImage`] for a missing or unreadable file or a failed decode,
/// [`MatchingError::CorruptImage`] with the reason for a broken one.
pub fn decode(path: &Path, flags: i32) -> Result<Mat> {
    let bytes = std::fs::read(path).map_err(|_| MatchingError::UnreadableImage {
        path: path.to_owned(),
    })?;
    if let Some(reason) = image_problem(&bytes) {
        return Err(MatchingError::CorruptImage {
            path: path.to_owned(),
            reason,
        });
    }
    let buf = Vector::<u8>::from_slice(&bytes);
    let img =
        opencv::imgcodecs::imdecode(&buf, flags).map_err(|_| MatchingError::UnreadableImage {
            path: path.to_owned(),
        })?;
    if img.empty() || img.cols() <= 0 || img.rows() <= 0 {
        return Err(MatchingError::UnreadableImage {
            path: path.to_owned(),
        });
    }
    Ok(img)
}
