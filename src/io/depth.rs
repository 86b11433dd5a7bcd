//! 16-bit depth images as PNG or TIFF, to and from [`DepthImage`].
//!
//! Depth cameras (RealSense, Kinect, PCL's grabber files) store one unsigned 16-bit value per
//! pixel in a fixed unit, 0 meaning no return. Neither format records that unit, so the
//! readers take it (`depth_scale_m`, 0.001 for millimetres). PNG must be single-channel
//! 16-bit greyscale (samples are big-endian in the file; the `png` crate hands them over
//! as such); TIFF must be single-channel 16-bit greyscale, any compression the `tiff` crate
//! decodes. Images above [`ReadLimits::max_pixels`] are refused before any pixel buffer is
//! allocated, and so is a PNG whose declared size its compressed bytes cannot hold (deflate
//! expands at most 1032:1), so a forged header cannot exhaust memory. The depth unit and the
//! pinhole intrinsics a deprojection takes are checked here ([`check_depth_scale`],
//! [`check_intrinsics`]). Deprojection to a cloud is [`DepthImage::deproject`].

use super::{Error, FormatError, ReadLimits, read_bytes, write_bytes};
use crate::camera::{DepthImage, PinholeIntrinsics};
use std::io::Cursor;
use std::path::Path;

/// Accepted depth units, metres per count: from a micrometre to a metre (sensors use
/// 1e-4 to 1e-3; a metre per count already gives 65 km of range).
pub const DEPTH_SCALE_RANGE_M: (f64, f64) = (1e-6, 1.0);

/// Accepted focal lengths, pixels: below a pixel a pinhole camera would see more than 180
/// degrees across a few pixels (and tiny values deproject to infinities); real cameras are
/// below 1e5.
pub const FOCAL_RANGE_PX: (f64, f64) = (1.0, 1e6);

/// Deflate's largest expansion, output bytes per compressed byte.
const MAX_DEFLATE_RATIO: u64 = 1032;

/// `Ok` for a finite depth unit within [`DEPTH_SCALE_RANGE_M`]; the error names the value.
pub fn check_depth_scale(depth_scale_m: f64) -> Result<(), FormatError> {
    let (lo, hi) = DEPTH_SCALE_RANGE_M;
    if !(lo..=hi).contains(&depth_scale_m) {
        return Err(FormatError::BadValue(format!(
            "depth scale {depth_scale_m:?} m per unit is outside [{lo:?}, {hi:?}] m"
        )));
    }
    Ok(())
}

/// `Ok` for intrinsics that deproject: focal lengths within [`FOCAL_RANGE_PX`], the
/// principal point finite and inside the image, a non-empty image. The error names the value.
pub fn check_intrinsics(k: &PinholeIntrinsics) -> Result<(), FormatError> {
    if k.width == 0 || k.height == 0 {
        return Err(FormatError::BadValue(format!(
            "intrinsics for a {} x {} image",
            k.width, k.height
        )));
    }
    let (lo, hi) = FOCAL_RANGE_PX;
    for (name, value) in [("fx", k.fx), ("fy", k.fy)] {
        if !(lo..=hi).contains(&value) {
            return Err(FormatError::BadValue(format!(
                "focal length {name} = {value:?} px is not in [{lo:?}, {hi:?}]"
            )));
        }
    }
    for (name, value, size) in [("cx", k.cx, k.width), ("cy", k.cy, k.height)] {
        if !(0.0..=f64::from(size)).contains(&value) {
            return Err(FormatError::BadValue(format!(
                "principal point {name} = {value:?} px is outside the image [0, {size}]"
            )));
        }
    }
    Ok(())
}

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

fn check_size(width: u32, height: u32, limits: &ReadLimits) -> Result<usize, FormatError> {
    let pixels = u64::from(width) * u64::from(height);
    if pixels > limits.max_pixels {
        return Err(FormatError::Limit(format!(
            "{width} x {height} image has {pixels} pixels, the limit is {}",
            limits.max_pixels
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

/// Decode a 16-bit greyscale PNG within the default [`ReadLimits`].
pub fn png_from_bytes(bytes: &[u8], depth_scale_m: f64) -> Result<DepthImage, FormatError> {
    png_from_bytes_within(bytes, depth_scale_m, &ReadLimits::default())
}

/// Decode a 16-bit greyscale PNG; an image above `limits` is an error.
pub fn png_from_bytes_within(
    bytes: &[u8],
    depth_scale_m: f64,
    limits: &ReadLimits,
) -> Result<DepthImage, FormatError> {
    check_depth_scale(depth_scale_m)?;
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
    let pixels = check_size(width, height, limits)?;
    // Each row is a filter byte and the samples; all of it comes out of the deflate stream.
    let raw = u64::from(height) * (1 + 2 * u64::from(width));
    if raw > MAX_DEFLATE_RATIO * bytes.len() as u64 {
        return Err(FormatError::Truncated(format!(
            "{width} x {height} PNG needs {raw} decompressed bytes, its {} bytes hold at most {}",
            bytes.len(),
            MAX_DEFLATE_RATIO * bytes.len() as u64
        )));
    }
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

/// Decode a 16-bit greyscale TIFF (the first image of the file) within the default
/// [`ReadLimits`].
pub fn tiff_from_bytes(bytes: &[u8], depth_scale_m: f64) -> Result<DepthImage, FormatError> {
    tiff_from_bytes_within(bytes, depth_scale_m, &ReadLimits::default())
}

/// Decode a 16-bit greyscale TIFF; an image above `limits` is an error.
pub fn tiff_from_bytes_within(
    bytes: &[u8],
    depth_scale_m: f64,
    limits: &ReadLimits,
) -> Result<DepthImage, FormatError> {
    check_depth_scale(depth_scale_m)?;
    let mut decoder_limits = tiff::decoder::Limits::default();
    decoder_limits.decoding_buffer_size =
        usize::try_from(limits.max_pixels.saturating_mul(2)).unwrap_or(usize::MAX);
    let mut decoder = tiff::decoder::Decoder::new(Cursor::new(bytes))
        .map_err(codec)?
        .with_limits(decoder_limits);
    let (width, height) = decoder.dimensions().map_err(codec)?;
    let color = decoder.colortype().map_err(codec)?;
    if color != tiff::ColorType::Gray(16) {
        return Err(FormatError::Unsupported(format!(
            "TIFF is {color:?}, a depth image must be 16-bit greyscale"
        )));
    }
    let pixels = check_size(width, height, limits)?;
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

/// Read a 16-bit depth image (PNG or TIFF, by extension) whose unit is `depth_scale_m`,
/// within the default [`ReadLimits`].
pub fn read(path: &Path, depth_scale_m: f64) -> Result<DepthImage, Error> {
    read_within(path, depth_scale_m, &ReadLimits::default())
}

/// Read a 16-bit depth image; beyond `limits` (its size included) it is an error.
pub fn read_within(
    path: &Path,
    depth_scale_m: f64,
    limits: &ReadLimits,
) -> Result<DepthImage, Error> {
    let format = format_of(path)?;
    let bytes = read_bytes(path, limits)?;
    match format {
        ImageFormat::Png => png_from_bytes_within(&bytes, depth_scale_m, limits),
        ImageFormat::Tiff => tiff_from_bytes_within(&bytes, depth_scale_m, limits),
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

    /// `png` with its IHDR's size replaced (and the chunk's CRC recomputed).
    fn with_size(png: &[u8], width: u32, height: u32) -> Vec<u8> {
        // Signature (8), length (4), "IHDR" (4), then width and height.
        let mut out = png.to_vec();
        out[16..20].copy_from_slice(&width.to_be_bytes());
        out[20..24].copy_from_slice(&height.to_be_bytes());
        let crc = crc32fast::hash(&out[12..29]);
        out[29..33].copy_from_slice(&crc.to_be_bytes());
        out
    }

    #[test]
    fn declared_sizes_are_checked_before_the_pixel_buffer() {
        let png = png_to_bytes(&ramp()).unwrap();
        assert!(png_from_bytes(&with_size(&png, 7, 3), 0.001).is_ok());
        // 8192 x 8192: over the pixel limit, refused before decoding.
        let err = png_from_bytes(&with_size(&png, 8192, 8192), 0.001).unwrap_err();
        assert!(matches!(err, FormatError::Limit(_)), "{err}");
        assert!(err.to_string().contains("67108864 pixels"), "{err}");
        // Within the limit, but more than a PNG of this length can hold.
        let err = png_from_bytes(&with_size(&png, 2048, 2048), 0.001).unwrap_err();
        assert!(matches!(err, FormatError::Truncated(_)), "{err}");
        let tight = ReadLimits {
            max_pixels: 20,
            ..ReadLimits::default()
        };
        let err = png_from_bytes_within(&png, 0.001, &tight).unwrap_err();
        assert!(matches!(err, FormatError::Limit(_)), "{err}");
        let tiff = tiff_to_bytes(&ramp()).unwrap();
        let err = tiff_from_bytes_within(&tiff, 0.001, &tight).unwrap_err();
        assert!(matches!(err, FormatError::Limit(_)), "{err}");
    }

    #[test]
    fn depth_scale_outside_its_range_is_named() {
        let png = png_to_bytes(&ramp()).unwrap();
        let tiff = tiff_to_bytes(&ramp()).unwrap();
        for scale in [1e300, f64::NAN, f64::INFINITY, 0.0, -0.001, 1e-9] {
            for err in [
                png_from_bytes(&png, scale).unwrap_err(),
                tiff_from_bytes(&tiff, scale).unwrap_err(),
            ] {
                assert!(matches!(err, FormatError::BadValue(_)), "{err}");
                assert!(
                    err.to_string()
                        .contains(&format!("depth scale {scale:?} m per unit")),
                    "{err}"
                );
            }
        }
        for scale in [1e-6, 1e-4, 0.001, 1.0] {
            assert!(png_from_bytes(&png, scale).is_ok(), "{scale}");
        }
    }

    #[test]
    fn intrinsics_that_cannot_deproject_are_named() {
        assert!(check_intrinsics(&PinholeIntrinsics::PCL_GRABBER).is_ok());
        let k = PinholeIntrinsics::PCL_GRABBER;
        let cases = [
            (PinholeIntrinsics { fx: 0.0, ..k }, "fx = 0.0 px"),
            (PinholeIntrinsics { fy: f64::NAN, ..k }, "fy = NaN px"),
            (PinholeIntrinsics { fx: -525.0, ..k }, "fx = -525.0 px"),
            (PinholeIntrinsics { fy: 1e300, ..k }, "fy = 1e300 px"),
            (PinholeIntrinsics { fx: 1e-300, ..k }, "fx = 1e-300 px"),
            (PinholeIntrinsics { cx: f64::NAN, ..k }, "cx = NaN px"),
            (PinholeIntrinsics { cy: -1.0, ..k }, "cy = -1.0 px"),
            (PinholeIntrinsics { cx: 700.0, ..k }, "cx = 700.0 px"),
            (PinholeIntrinsics { width: 0, ..k }, "0 x 480 image"),
        ];
        for (k, expect) in cases {
            let err = check_intrinsics(&k).unwrap_err();
            assert!(err.to_string().contains(expect), "{err}");
        }
    }

    #[test]
    fn inconsistent_image_is_refused() {
        let mut image = ramp();
        image.data.pop();
        assert!(png_to_bytes(&image).is_err());
        assert!(tiff_to_bytes(&image).is_err());
    }
}
