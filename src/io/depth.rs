//! 16-bit depth images as PNG or TIFF, to and from [`DepthImage`].
//!
//! Depth cameras (RealSense, Kinect, PCL's grabber files) store one unsigned 16-bit value per
//! pixel in a fixed unit, 0 meaning no return. Neither format records that unit, so the
//! readers take it (`depth_scale_m`, 0.001 for millimetres). PNG must be single-channel
//! 16-bit greyscale (samples are big-endian in the file; the `png` crate hands them over
//! as such); TIFF must be single-channel 16-bit greyscale, any compression the `tiff` crate
//! decodes. Images above [`MAX_PIXELS`] are refused before any pixel buffer is allocated,
//! so a forged header cannot exhaust memory. Deprojection to a cloud is
//! [`DepthImage::deproject`].

use super::{Error, FormatError, read_bytes, write_bytes};
use crate::camera::DepthImage;
use std::io::Cursor;
use std::path::Path;

/// Largest accepted image, pixels (8192 x 8192; depth sensors deliver at most ~1 Mpx).
pub const MAX_PIXELS: u64 = 1 << 26;

/// The two image formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageFormat {
    Png,
    Tiff,
}

impl ImageFormat {
    /// The format named by a path's extension (`.png`, `.tif`, `.tiff`, any case).
    pub fn from_path(path: &Path) -> Option<Self> {
        let ext = path.extension()?.to_str()?.to_ascii_lowercase();
        match ext.as_str() {
            "png" => Some(Self::Png),
            "tif" | "tiff" => Some(Self::Tiff),
            _ => None,
        }
    }
}

fn codec(e: impl std::fmt::Display) -> FormatError {
    FormatError::Codec(e.to_string())
}

fn check_size(width: u32, height: u32) -> Result<usize, FormatError> {
    let pixels = u64::from(width) * u64::from(height);
    if pixels > MAX_PIXELS {
        return Err(FormatError::Unsupported(format!(
            "{width} x {height} image is larger than {MAX_PIXELS} pixels"
        )));
    }
    Ok(pixels as usize)
}

fn check_image(image: &DepthImage) -> Result<(), FormatError> {
    if image.data.len() as u64 != u64::from(image.width) * u64::from(image.height) {
        return Err(FormatError::InvalidCloud(format!(
            "depth image {} x {} holds {} pixels",
            image.width,
            image.height,
            image.data.len()
        )));
    }
    Ok(())
}

/// Decode a 16-bit greyscale PNG.
pub fn png_from_bytes(bytes: &[u8], depth_scale_m: f64) -> Result<DepthImage, FormatError> {
    let reader = png::Decoder::new(Cursor::new(bytes));
    let mut reader = reader.read_info().map_err(codec)?;
    let info = reader.info();
    let (width, height) = (info.width, info.height);
    if info.color_type != png::ColorType::Grayscale || info.bit_depth != png::BitDepth::Sixteen {
        return Err(FormatError::Unsupported(format!(
            "PNG is {:?} {:?}-bit, a depth image must be 16-bit greyscale",
            info.color_type, info.bit_depth as u8
        )));
    }
    let pixels = check_size(width, height)?;
    let mut buf = vec![0u8; pixels * 2];
    reader.next_frame(&mut buf).map_err(codec)?;
    Ok(DepthImage {
        width,
        height,
        depth_scale_m,
        data: buf
            .chunks_exact(2)
            .map(|b| u16::from_be_bytes([b[0], b[1]]))
            .collect(),
    })
}

/// Encode a depth image as a 16-bit greyscale PNG.
pub fn png_to_bytes(image: &DepthImage) -> Result<Vec<u8>, FormatError> {
    check_image(image)?;
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(&mut out, image.width, image.height);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Sixteen);
    let mut writer = encoder.write_header().map_err(codec)?;
    let bytes: Vec<u8> = image.data.iter().flat_map(|v| v.to_be_bytes()).collect();
    writer.write_image_data(&bytes).map_err(codec)?;
    writer.finish().map_err(codec)?;
    Ok(out)
}

/// Decode a 16-bit greyscale TIFF (the first image of the file).
pub fn tiff_from_bytes(bytes: &[u8], depth_scale_m: f64) -> Result<DepthImage, FormatError> {
    let mut decoder = tiff::decoder::Decoder::new(Cursor::new(bytes)).map_err(codec)?;
    let (width, height) = decoder.dimensions().map_err(codec)?;
    let color = decoder.colortype().map_err(codec)?;
    if color != tiff::ColorType::Gray(16) {
        return Err(FormatError::Unsupported(format!(
            "TIFF is {color:?}, a depth image must be 16-bit greyscale"
        )));
    }
    let pixels = check_size(width, height)?;
    let data = match decoder.read_image().map_err(codec)? {
        tiff::decoder::DecodingResult::U16(data) => data,
        _ => return Err(FormatError::Unsupported("TIFF samples are not u16".into())),
    };
    if data.len() != pixels {
        return Err(FormatError::CountMismatch(format!(
            "{width} x {height} TIFF decoded to {} samples",
            data.len()
        )));
    }
    Ok(DepthImage {
        width,
        height,
        depth_scale_m,
        data,
    })
}

/// Encode a depth image as an uncompressed 16-bit greyscale TIFF.
pub fn tiff_to_bytes(image: &DepthImage) -> Result<Vec<u8>, FormatError> {
    check_image(image)?;
    let mut out = Cursor::new(Vec::new());
    let mut encoder = tiff::encoder::TiffEncoder::new(&mut out).map_err(codec)?;
    encoder
        .write_image::<tiff::encoder::colortype::Gray16>(image.width, image.height, &image.data)
        .map_err(codec)?;
    Ok(out.into_inner())
}

fn format_of(path: &Path) -> Result<ImageFormat, Error> {
    ImageFormat::from_path(path).ok_or_else(|| {
        FormatError::Unsupported(
            "unknown depth-image extension (expected .png, .tif, .tiff)".into(),
        )
        .at(path)
    })
}

/// Read a 16-bit depth image (PNG or TIFF, by extension) whose unit is `depth_scale_m`.
pub fn read(path: &Path, depth_scale_m: f64) -> Result<DepthImage, Error> {
    let format = format_of(path)?;
    let bytes = read_bytes(path)?;
    match format {
        ImageFormat::Png => png_from_bytes(&bytes, depth_scale_m),
        ImageFormat::Tiff => tiff_from_bytes(&bytes, depth_scale_m),
    }
    .map_err(|e| e.at(path))
}

/// Write a 16-bit depth image (PNG or TIFF, by extension).
pub fn write(path: &Path, image: &DepthImage) -> Result<(), Error> {
    let bytes = match format_of(path)? {
        ImageFormat::Png => png_to_bytes(image),
        ImageFormat::Tiff => tiff_to_bytes(image),
    }
    .map_err(|e| e.at(path))?;
    write_bytes(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp() -> DepthImage {
        DepthImage {
            width: 7,
            height: 3,
            depth_scale_m: 0.001,
            data: (0..21u16).map(|i| i.wrapping_mul(3121)).collect(),
        }
    }

    #[test]
    fn png_and_tiff_round_trip() {
        let image = ramp();
        assert_eq!(
            png_from_bytes(&png_to_bytes(&image).unwrap(), 0.001).unwrap(),
            image
        );
        assert_eq!(
            tiff_from_bytes(&tiff_to_bytes(&image).unwrap(), 0.001).unwrap(),
            image
        );
    }

    #[test]
    fn eight_bit_png_is_refused() {
        let mut out = Vec::new();
        let mut encoder = png::Encoder::new(&mut out, 2, 1);
        encoder.set_color(png::ColorType::Grayscale);
        encoder.set_depth(png::BitDepth::Eight);
        let mut w = encoder.write_header().unwrap();
        w.write_image_data(&[1, 2]).unwrap();
        w.finish().unwrap();
        let err = png_from_bytes(&out, 0.001).unwrap_err();
        assert!(err.to_string().contains("16-bit greyscale"), "{err}");
    }

    #[test]
    fn truncated_images_fail() {
        let image = ramp();
        // A PNG is complete before its 12-byte IEND chunk; cut into the pixel data.
        let png = png_to_bytes(&image).unwrap();
        for cut in [0, 8, png.len() / 2, png.len() - 13] {
            assert!(
                png_from_bytes(&png[..cut], 0.001).is_err(),
                "png cut at {cut}"
            );
        }
        let tiff = tiff_to_bytes(&image).unwrap();
        for cut in [0, 8, tiff.len() / 2, tiff.len() - 1] {
            assert!(
                tiff_from_bytes(&tiff[..cut], 0.001).is_err(),
                "tiff cut at {cut}"
            );
        }
        assert!(png_from_bytes(&tiff, 0.001).is_err());
        assert!(tiff_from_bytes(&png, 0.001).is_err());
    }

    #[test]
    fn inconsistent_image_is_refused() {
        let mut image = ramp();
        image.data.pop();
        assert!(png_to_bytes(&image).is_err());
        assert!(tiff_to_bytes(&image).is_err());
    }
}
