//! The camera an image's EXIF names and its focal tags, read with `kamadak-exif` (JPEG, PNG,
//! WebP, HEIF); the pipeline turns them into camera groups and focal priors
//! ([`ExifFocal::prior`] has COLMAP's conversion to pixels).
//!
//! [`write_jpeg_exif`] and [`write_png_exif`] write such tags into copies of images (the
//! variants and the tests: the shared sets carry no EXIF).

use std::path::Path;

use exif::{Field, In, Tag, Value};

use posediff_pipeline::options::{CameraHint, ExifFocal};

use crate::error::{PosediffError, Result};

/// What an image's EXIF says about its camera.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ExifCamera {
    /// `Make`, trimmed ("" when absent).
    pub make: String,
    /// `Model`, trimmed ("" when absent).
    pub model: String,
    /// The focal tags (their conversion to pixels: [`ExifFocal::prior`]).
    pub focal: ExifFocal,
}

impl ExifCamera {
    /// The camera's identity for grouping: make, model and focal length (a zoom lens at
    /// another focal is another camera, as in COLMAP's per-EXIF grouping).
    pub fn device(&self) -> String {
        let focal = self
            .focal
            .focal_mm
            .or(self.focal.focal_35mm)
            .map_or_else(String::new, |f| format!(" {f:.2} mm"));
        format!("{} {}{focal}", self.make, self.model)
            .trim()
            .to_owned()
    }

    /// The pipeline's hint for an image in `folder` with this EXIF.
    pub fn hint(exif: Option<&Self>, folder: String) -> CameraHint {
        CameraHint {
            folder,
            device: exif.map(Self::device),
            focal: exif.map(|e| e.focal).unwrap_or_default(),
        }
    }
}

/// The EXIF of `path`, or `None` when the file has none or none that parses (logged: a broken
/// EXIF block must not stop a run that does not need it).
///
/// # Errors
/// The file cannot be opened.
pub fn read_exif(path: &Path) -> Result<Option<ExifCamera>> {
    let file = std::fs::File::open(path).map_err(|e| PosediffError::Read {
        path: path.to_owned(),
        source: e,
    })?;
    let exif = match exif::Reader::new().read_from_container(&mut std::io::BufReader::new(file)) {
        Ok(e) => e,
        Err(exif::Error::NotFound(_)) => return Ok(None),
        Err(e) => {
            log::warn!("{}: EXIF ignored ({e})", path.display());
            return Ok(None);
        }
    };
    let text = |tag| {
        exif.get_field(tag, In::PRIMARY)
            .and_then(|f| match &f.value {
                Value::Ascii(parts) => parts
                    .first()
                    .map(|s| String::from_utf8_lossy(s).trim().to_owned()),
                _ => None,
            })
            .unwrap_or_default()
    };
    let number = |tag| {
        exif.get_field(tag, In::PRIMARY)
            .and_then(|f| match &f.value {
                Value::Rational(v) => v.first().map(exif::Rational::to_f64),
                Value::SRational(v) => v.first().map(exif::SRational::to_f64),
                v => v.get_uint(0).map(f64::from),
            })
    };
    // FocalPlaneResolutionUnit: 2 inch (the default), 3 cm, 4 mm, 5 µm.
    let mm_per_unit = match exif
        .get_field(Tag::FocalPlaneResolutionUnit, In::PRIMARY)
        .and_then(|f| f.value.get_uint(0))
        .unwrap_or(2)
    {
        3 => Some(10.0),
        4 => Some(1.0),
        5 => Some(1e-3),
        2 => Some(25.4),
        _ => None,
    };
    let camera = ExifCamera {
        make: text(Tag::Make),
        model: text(Tag::Model),
        focal: ExifFocal {
            focal_mm: number(Tag::FocalLength),
            focal_35mm: number(Tag::FocalLengthIn35mmFilm),
            focal_plane_px_per_mm: number(Tag::FocalPlaneXResolution)
                .zip(mm_per_unit)
                .map(|(r, mm)| r / mm),
            pixel_width: exif
                .get_field(Tag::PixelXDimension, In::PRIMARY)
                .and_then(|f| f.value.get_uint(0)),
        },
    };
    let any = !camera.make.is_empty()
        || !camera.model.is_empty()
        || camera.focal.focal_mm.is_some()
        || camera.focal.focal_35mm.is_some();
    Ok(any.then_some(camera))
}

/// The TIFF-structured EXIF block of `camera` (what APP1 and eXIf carry).
fn exif_block(camera: &ExifCamera) -> Result<Vec<u8>> {
    let rational = |v: f64| {
        // Millimetres to 1/1000 mm: exact enough for a focal, within u32.
        let num = (v * 1000.0).round().clamp(0.0, f64::from(u32::MAX)) as u32;
        Value::Rational(vec![exif::Rational { num, denom: 1000 }])
    };
    let mut fields = vec![
        Field {
            tag: Tag::Make,
            ifd_num: In::PRIMARY,
            value: Value::Ascii(vec![camera.make.clone().into_bytes()]),
        },
        Field {
            tag: Tag::Model,
            ifd_num: In::PRIMARY,
            value: Value::Ascii(vec![camera.model.clone().into_bytes()]),
        },
    ];
    if let Some(f) = camera.focal.focal_mm {
        fields.push(Field {
            tag: Tag::FocalLength,
            ifd_num: In::PRIMARY,
            value: rational(f),
        });
    }
    if let Some(f) = camera.focal.focal_35mm {
        fields.push(Field {
            tag: Tag::FocalLengthIn35mmFilm,
            ifd_num: In::PRIMARY,
            value: Value::Short(vec![f.round().clamp(1.0, 65535.0) as u16]),
        });
    }
    if let Some(r) = camera.focal.focal_plane_px_per_mm {
        fields.push(Field {
            tag: Tag::FocalPlaneXResolution,
            ifd_num: In::PRIMARY,
            value: rational(r),
        });
        fields.push(Field {
            tag: Tag::FocalPlaneResolutionUnit,
            ifd_num: In::PRIMARY,
            value: Value::Short(vec![4]),
        });
    }
    if let Some(w) = camera.focal.pixel_width {
        fields.push(Field {
            tag: Tag::PixelXDimension,
            ifd_num: In::PRIMARY,
            value: Value::Long(vec![w]),
        });
    }
    let mut writer = exif::experimental::Writer::new();
    for f in &fields {
        writer.push_field(f);
    }
    let mut out = std::io::Cursor::new(Vec::new());
    writer
        .write(&mut out, false)
        .map_err(|e| PosediffError::InvalidArgument(format!("writing EXIF: {e}")))?;
    Ok(out.into_inner())
}

/// `jpeg` with an APP1 EXIF segment of `camera` right after its start marker (any EXIF it
/// had stays after it; readers take the first).
///
/// # Errors
/// Not a JPEG; an EXIF block over 64 KiB.
pub fn write_jpeg_exif(jpeg: &[u8], camera: &ExifCamera) -> Result<Vec<u8>> {
    let Some(rest) = jpeg.strip_prefix(&[0xFF, 0xD8]) else {
        return Err(PosediffError::InvalidArgument(
            "EXIF goes into JPEG files only here: the data does not start with FF D8".into(),
        ));
    };
    let block = exif_block(camera)?;
    let length = u16::try_from(block.len() + 8)
        .map_err(|_| PosediffError::InvalidArgument("EXIF block over 64 KiB".into()))?;
    let mut out = Vec::with_capacity(jpeg.len() + block.len() + 10);
    out.extend_from_slice(&[0xFF, 0xD8, 0xFF, 0xE1]);
    out.extend_from_slice(&length.to_be_bytes());
    out.extend_from_slice(b"Exif\0\0");
    out.extend_from_slice(&block);
    out.extend_from_slice(rest);
    Ok(out)
}

/// `png` with an `eXIf` chunk of `camera` after its header chunk.
///
/// # Errors
/// Not a PNG.
pub fn write_png_exif(png: &[u8], camera: &ExifCamera) -> Result<Vec<u8>> {
    const SIGNATURE: &[u8] = b"\x89PNG\r\n\x1a\n";
    // Signature, then IHDR: 4 length + 4 type + 13 data + 4 CRC.
    let header_end = SIGNATURE.len() + 25;
    if !png.starts_with(SIGNATURE) || png.len() < header_end || &png[12..16] != b"IHDR" {
        return Err(PosediffError::InvalidArgument(
            "not a PNG with its IHDR chunk first".into(),
        ));
    }
    let block = exif_block(camera)?;
    let length = u32::try_from(block.len())
        .map_err(|_| PosediffError::InvalidArgument("EXIF block too large".into()))?;
    let mut chunk = Vec::with_capacity(block.len() + 12);
    chunk.extend_from_slice(&length.to_be_bytes());
    chunk.extend_from_slice(b"eXIf");
    chunk.extend_from_slice(&block);
    let crc = crc32fast::hash(&chunk[4..]);
    chunk.extend_from_slice(&crc.to_be_bytes());
    let mut out = Vec::with_capacity(png.len() + chunk.len());
    out.extend_from_slice(&png[..header_end]);
    out.extend_from_slice(&chunk);
    out.extend_from_slice(&png[header_end..]);
    Ok(out)
}

/// `bytes` (a JPEG or PNG file's) with `camera`'s EXIF.
///
/// # Errors
/// Neither JPEG nor PNG.
pub fn with_exif(bytes: &[u8], camera: &ExifCamera) -> Result<Vec<u8>> {
    if bytes.starts_with(&[0xFF, 0xD8]) {
        write_jpeg_exif(bytes, camera)
    } else {
        write_png_exif(bytes, camera)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn camera() -> ExifCamera {
        ExifCamera {
            make: "Acme".into(),
            model: "Phone 7".into(),
            focal: ExifFocal {
                focal_mm: Some(4.25),
                focal_35mm: Some(26.0),
                focal_plane_px_per_mm: Some(735.5),
                pixel_width: Some(4032),
            },
        }
    }

    #[test]
    fn the_device_names_make_model_and_focal() {
        assert_eq!(camera().device(), "Acme Phone 7 4.25 mm");
        let hint = ExifCamera::hint(None, "a".into());
        assert_eq!((hint.device, hint.folder.as_str()), (None, "a"));
    }

    #[test]
    fn tags_written_into_jpeg_and_png_read_back() {
        let dir = std::env::temp_dir().join(format!("posediff-exif-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let image = opencv::core::Mat::new_rows_cols_with_default(
            24,
            32,
            opencv::core::CV_8UC3,
            opencv::core::Scalar::all(90.0),
        )
        .unwrap();
        for ext in ["jpg", "png"] {
            let mut plain = opencv::core::Vector::<u8>::new();
            opencv::imgcodecs::imencode(
                &format!(".{ext}"),
                &image,
                &mut plain,
                &opencv::core::Vector::new(),
            )
            .unwrap();
            let path = dir.join(format!("a.{ext}"));
            std::fs::write(&path, plain.as_slice()).unwrap();
            assert_eq!(read_exif(&path).unwrap(), None, "{ext}: no EXIF yet");
            std::fs::write(&path, with_exif(plain.as_slice(), &camera()).unwrap()).unwrap();
            let back = read_exif(&path).unwrap().unwrap();
            assert_eq!(back.make, "Acme");
            assert_eq!(back.model, "Phone 7");
            assert_eq!(back.focal, camera().focal);
            // The image still decodes, at its size.
            let decoded =
                opencv::imgcodecs::imread(path.to_str().unwrap(), opencv::imgcodecs::IMREAD_COLOR)
                    .unwrap();
            use opencv::prelude::MatTraitConst;
            assert_eq!((decoded.cols(), decoded.rows()), (32, 24), "{ext}");
        }
        std::fs::remove_dir_all(&dir).ok();
    }
}
