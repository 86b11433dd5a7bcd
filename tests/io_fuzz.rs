//! No reader of `hapcloud::io` panics, whatever the bytes: random input, and valid files of
//! every format and encoding truncated and with bytes overwritten (which reaches deep into
//! headers, LZF streams and image codecs). Each reader must return `Ok` or `Err`.

use glam::Vec3;
use hapcloud::camera::DepthImage;
use hapcloud::cloud::PointCloud;
use hapcloud::io::{Encoding, depth, pcd, ply};
use proptest::prelude::*;
use std::sync::LazyLock;

/// Valid files of every format and encoding, built once.
static SEEDS: LazyLock<Vec<Vec<u8>>> = LazyLock::new(|| {
    let points: Vec<Vec3> = (0..24)
        .map(|i| {
            Vec3::new(
                i as f32 * 0.1,
                (i % 5) as f32,
                if i % 7 == 0 { f32::NAN } else { 1.0 },
            )
        })
        .collect();
    let mut cloud = PointCloud::organized(points, 6, 4).unwrap();
    cloud.rgba = Some((0..24).map(|i| i * 0x0101_0101).collect());
    cloud.normals = Some(vec![Vec3::Z; 24]);
    let mut seeds = Vec::new();
    for enc in [
        Encoding::Ascii,
        Encoding::Binary,
        Encoding::BinaryCompressed,
    ] {
        seeds.push(pcd::to_bytes(&cloud, enc).unwrap());
    }
    for enc in [
        ply::Encoding::Ascii,
        ply::Encoding::BinaryLittleEndian,
        ply::Encoding::BinaryBigEndian,
    ] {
        seeds.push(ply::to_bytes(&cloud, enc).unwrap());
    }
    let image = DepthImage {
        width: 5,
        height: 4,
        depth_scale_m: 0.001,
        data: (0..20).map(|i| i * 1000).collect(),
    };
    seeds.push(depth::png_to_bytes(&image).unwrap());
    seeds.push(depth::tiff_to_bytes(&image).unwrap());
    seeds
});

/// Runs every reader on `bytes`; a panic fails the property.
fn read_all(bytes: &[u8]) {
    let _ = pcd::from_bytes(bytes);
    let _ = ply::from_bytes(bytes);
    let _ = depth::png_from_bytes(bytes, 0.001);
    let _ = depth::tiff_from_bytes(bytes, 0.001);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
        read_all(&bytes);
    }

    #[test]
    fn damaged_files_never_panic(
        seed in 0usize..8,
        cut in 0.0f64..=1.0,
        edits in proptest::collection::vec((0.0f64..1.0, any::<u8>()), 0..6),
    ) {
        let mut bytes = SEEDS[seed].clone();
        for (at, value) in edits {
            let len = bytes.len();
            bytes[((at * len as f64) as usize).min(len - 1)] = value;
        }
        bytes.truncate((cut * bytes.len() as f64) as usize);
        read_all(&bytes);
    }

    /// A PCD header with any digits in its numeric fields must not panic or allocate wildly.
    #[test]
    fn forged_pcd_numbers_never_panic(
        width in any::<u32>(),
        height in any::<u32>(),
        points in any::<u64>(),
        count in prop_oneof![any::<u32>(), 1u32..=(1 << 20)],
        sizes in (0u64..10, 0u64..10),
        words in (any::<u32>(), any::<u32>()),
        encoding in 0usize..3,
    ) {
        let name = ["ascii", "binary", "binary_compressed"][encoding];
        let mut bytes = format!(
            "FIELDS x y z w\nSIZE 4 4 {} {}\nTYPE F F F U\nCOUNT 1 1 1 {count}\nWIDTH {width}\n\
             HEIGHT {height}\nPOINTS {points}\nDATA {name}\n",
            sizes.0, sizes.1
        )
        .into_bytes();
        bytes.extend_from_slice(&words.0.to_le_bytes());
        bytes.extend_from_slice(&words.1.to_le_bytes());
        bytes.extend_from_slice(&[0x1f; 64]);
        let _ = pcd::from_bytes(&bytes);
    }

    /// A PLY header with any element counts and list types, over random data.
    #[test]
    fn forged_ply_numbers_never_panic(
        vertices in any::<u64>(),
        faces in any::<u64>(),
        list_type in 0usize..4,
        format in 0usize..3,
        body in proptest::collection::vec(any::<u8>(), 0..256),
    ) {
        let format = ["ascii", "binary_little_endian", "binary_big_endian"][format];
        let count = ["uchar", "ushort", "uint", "float"][list_type];
        let mut bytes = format!(
            "ply\nformat {format} 1.0\nelement face {faces}\nproperty list {count} int idx\n\
             element vertex {vertices}\nproperty float x\nproperty float y\nproperty float z\n\
             end_header\n"
        )
        .into_bytes();
        bytes.extend_from_slice(&body);
        let _ = ply::from_bytes(&bytes);
    }
}

#[test]
fn seeds_are_valid() {
    for (i, seed) in SEEDS.iter().enumerate() {
        let ok = match i {
            0..=2 => pcd::from_bytes(seed).is_ok(),
            3..=5 => ply::from_bytes(seed).is_ok(),
            6 => depth::png_from_bytes(seed, 0.001).is_ok(),
            _ => depth::tiff_from_bytes(seed, 0.001).is_ok(),
        };
        assert!(ok, "seed {i}");
    }
}
