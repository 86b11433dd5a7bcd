//! The readers and writers of `hapcloud::io` on PCL's own test files (../shared/data/pcl),
//! checked against PCL itself where pcl-tools is installed (CI installs it).

use glam::Vec3;
use hapcloud::camera::PinholeIntrinsics;
use hapcloud::cloud::PointCloud;
use hapcloud::io::{self, Encoding, depth, pcd, ply};
use std::path::{Path, PathBuf};
use std::process::Command;

fn data(rel: &str) -> PathBuf {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/pcl")).join(rel)
}

const GRABBER_STAMPS: [&str; 3] = [
    "20121214T142255.814212",
    "20121214T142256.068683",
    "20121214T142256.332395",
];

/// Every PCD file of the data set with (width, height, has colour, has normals).
fn pcd_files() -> Vec<(PathBuf, u32, u32, bool, bool)> {
    let mut files = vec![
        (data("bun0.pcd"), 397, 1, false, true),
        (data("bun4.pcd"), 361, 1, false, false),
        (data("milk.pcd"), 13704, 1, false, false),
        (data("sac_plane_test.pcd"), 3283, 1, false, true),
        (
            data("table_scene_mug_stereo_textured.pcd"),
            640,
            480,
            true,
            false,
        ),
        (data("five_people.pcd"), 640, 480, true, false),
        (data("office1.pcd"), 640, 480, true, false),
    ];
    for stamp in GRABBER_STAMPS {
        let path = data(&format!("grabber_sequences/pcd/frame_{stamp}.pcd"));
        files.push((path, 640, 480, true, false));
    }
    files
}

#[test]
fn reads_every_pcl_pcd_file() {
    for (path, width, height, color, normals) in pcd_files() {
        let cloud = pcd::read(&path).unwrap();
        let name = path.display();
        assert_eq!((cloud.width, cloud.height), (width, height), "{name}");
        assert_eq!(cloud.len(), (width * height) as usize, "{name}");
        assert_eq!(cloud.rgba.is_some(), color, "{name}");
        assert_eq!(cloud.normals.is_some(), normals, "{name}");
        assert!(cloud.finite_count() > cloud.len() / 2, "{name}");
    }
    let bun0 = pcd::read(&data("bun0.pcd")).unwrap();
    assert_eq!(bun0.finite_count(), 397);
    // The centroid PCL's tests assert for bun0.
    let sum = bun0.points.iter().fold(nalgebra::Vector3::zeros(), |s, p| {
        s + nalgebra::Vector3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z))
    });
    let centroid = sum / 397.0;
    let expected = nalgebra::Vector3::new(-0.0290809, 0.102653, 0.027302);
    assert!((centroid - expected).amax() < 1e-6, "{centroid}");
    // The grabber frames' VIEWPOINT `0 0 0 0 1 0 0` is a half turn about x.
    let table = pcd::read(&data("table_scene_mug_stereo_textured.pcd")).unwrap();
    let q = table.sensor_pose.rotation;
    assert!((q.angle() - std::f64::consts::PI).abs() < 1e-12);
    assert!((q.axis().unwrap().x.abs() - 1.0).abs() < 1e-12);
}

fn pcl_tool(name: &str) -> Option<Command> {
    let available = Command::new("sh")
        .args(["-c", &format!("command -v {name}")])
        .output()
        .is_ok_and(|o| o.status.success());
    if !available {
        eprintln!("{name} not installed (apt-get install pcl-tools); PCL comparison skipped");
    }
    available.then(|| Command::new(name))
}

fn run(mut cmd: Command) {
    let out = cmd.output().unwrap();
    assert!(
        out.status.success(),
        "{cmd:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Bit-for-bit equality of two clouds' points (NaN positions included) and fields.
fn assert_same_cloud(a: &PointCloud, b: &PointCloud, what: &str) {
    assert_eq!(a.len(), b.len(), "{what}");
    assert_eq!((a.width, a.height), (b.width, b.height), "{what}");
    let first_difference = |p: &[Vec3], q: &[Vec3]| {
        let bits = |v: &Vec3| v.to_array().map(f32::to_bits);
        p.iter().zip(q).position(|(u, v)| bits(u) != bits(v))
    };
    assert_eq!(
        first_difference(&a.points, &b.points),
        None,
        "{what}: points"
    );
    assert_eq!(a.rgba.is_some(), b.rgba.is_some(), "{what}");
    let colour_diff =
        (a.rgba.iter().flatten().zip(b.rgba.iter().flatten())).position(|(u, v)| u != v);
    assert_eq!(colour_diff, None, "{what}: colours");
    match (&a.normals, &b.normals) {
        (Some(n), Some(m)) => assert_eq!(first_difference(n, m), None, "{what}: normals"),
        (None, None) => {}
        _ => panic!("{what}: only one cloud has normals"),
    }
}

fn scratch(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("io_real_data");
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// PCL converts each file to ASCII with 9 significant digits (exact for f32); our decode of
/// the original (binary_compressed LZF, ascii) must equal our read of PCL's ASCII bit for bit.
#[test]
fn decodes_like_pcl() {
    if pcl_tool("pcl_convert_pcd_ascii_binary").is_none() {
        return;
    }
    for (path, ..) in pcd_files() {
        let ours = pcd::read(&path).unwrap();
        let ascii = scratch(&format!(
            "pcl_{}",
            path.file_name().unwrap().to_string_lossy()
        ));
        let mut cmd = pcl_tool("pcl_convert_pcd_ascii_binary").unwrap();
        cmd.arg(&path).arg(&ascii).args(["0", "9"]);
        run(cmd);
        let theirs = pcd::read(&ascii).unwrap();
        assert_same_cloud(&ours, &theirs, &path.display().to_string());
    }
}

/// PCL's own binary and binary_compressed writers (bun0: seven fields with normals and
/// curvature; table_scene: organized with rgba) read back to the original's points.
#[test]
fn reads_pcl_binary_writers() {
    if pcl_tool("pcl_convert_pcd_ascii_binary").is_none() {
        return;
    }
    for file in ["bun0.pcd", "table_scene_mug_stereo_textured.pcd"] {
        let original = pcd::read(&data(file)).unwrap();
        for (mode, name) in [("1", "binary"), ("2", "binary_compressed")] {
            let out = scratch(&format!("pcl_{name}_{file}"));
            let mut cmd = pcl_tool("pcl_convert_pcd_ascii_binary").unwrap();
            cmd.arg(data(file)).arg(&out).arg(mode);
            run(cmd);
            let header = std::fs::read(&out).unwrap();
            let data_line = format!("DATA {name}\n");
            assert!(
                header
                    .windows(data_line.len())
                    .any(|w| w == data_line.as_bytes())
            );
            assert_same_cloud(
                &original,
                &pcd::read(&out).unwrap(),
                &format!("{file} {name}"),
            );
        }
    }
}

/// What we write loads in PCL: PCL re-encodes our files as ASCII and gets our points back,
/// and `pcl_voxel_grid` gives the same output count on our binary_compressed copy as on the
/// original file.
#[test]
fn pcl_reads_what_we_write() {
    if pcl_tool("pcl_convert_pcd_ascii_binary").is_none() || pcl_tool("pcl_voxel_grid").is_none() {
        return;
    }
    let original = data("table_scene_mug_stereo_textured.pcd");
    let cloud = pcd::read(&original).unwrap();
    for (enc, name) in [
        (Encoding::Ascii, "ascii"),
        (Encoding::Binary, "binary"),
        (Encoding::BinaryCompressed, "binary_compressed"),
    ] {
        let ours = scratch(&format!("ours_{name}.pcd"));
        pcd::write(&ours, &cloud, enc).unwrap();
        let back = scratch(&format!("ours_{name}_via_pcl.pcd"));
        let mut cmd = pcl_tool("pcl_convert_pcd_ascii_binary").unwrap();
        cmd.arg(&ours).arg(&back).args(["0", "9"]);
        run(cmd);
        assert_same_cloud(&cloud, &pcd::read(&back).unwrap(), name);
    }
    let voxel_count = |input: &Path, out: &str| {
        let out = scratch(out);
        let mut cmd = pcl_tool("pcl_voxel_grid").unwrap();
        cmd.arg(input).arg(&out).args(["-leaf", "0.01,0.01,0.01"]);
        run(cmd);
        pcd::read(&out).unwrap().len()
    };
    let reference = voxel_count(&original, "voxel_original.pcd");
    let ours = voxel_count(&scratch("ours_binary_compressed.pcd"), "voxel_ours.pcd");
    assert!(reference > 1000);
    assert_eq!(ours, reference);
}

/// PLY both ways through PCL: `pcl_pcd2ply` output reads back to the PCD's points, and our
/// PLY converts with `pcl_ply2pcd` to the same points.
#[test]
fn ply_interoperates_with_pcl() {
    if pcl_tool("pcl_pcd2ply").is_none() || pcl_tool("pcl_ply2pcd").is_none() {
        return;
    }
    for file in ["bun0.pcd", "milk.pcd"] {
        let cloud = pcd::read(&data(file)).unwrap();
        for format in ["0", "1"] {
            let out = scratch(&format!("pcl_{file}_{format}.ply"));
            let mut cmd = pcl_tool("pcl_pcd2ply").unwrap();
            cmd.args(["-format", format]).arg(data(file)).arg(&out);
            run(cmd);
            let back = ply::read(&out).unwrap();
            assert_eq!(back.len(), cloud.len(), "{file}");
            let max = back
                .points
                .iter()
                .zip(&cloud.points)
                .map(|(a, b)| (*a - *b).abs().max_element())
                .fold(0.0f32, f32::max);
            // PCL's ASCII PLY keeps ~7 significant digits; binary is exact.
            assert!(max <= 1e-6, "{file} format {format}: max deviation {max}");
        }
        let ours = scratch(&format!("ours_{file}.ply"));
        ply::write(&ours, &cloud, ply::Encoding::BinaryLittleEndian).unwrap();
        let via = scratch(&format!("ours_{file}_via_pcl.pcd"));
        let mut cmd = pcl_tool("pcl_ply2pcd").unwrap();
        cmd.arg(&ours).arg(&via);
        run(cmd);
        assert_eq!(pcd::read(&via).unwrap().points, cloud.points, "{file}");
    }
    // An organized RGBA frame: PCL's PLY (with its camera element) keeps the 640 x 480
    // layout and the colours, and PCL reads our PLY's layout back.
    let table = data("table_scene_mug_stereo_textured.pcd");
    let cloud = pcd::read(&table).unwrap();
    let out = scratch("pcl_table.ply");
    let mut cmd = pcl_tool("pcl_pcd2ply").unwrap();
    cmd.args(["-format", "1"]).arg(&table).arg(&out);
    run(cmd);
    let back = ply::read(&out).unwrap();
    let mut expected = cloud.clone();
    expected.sensor_pose = back.sensor_pose; // pcl_pcd2ply does not carry the VIEWPOINT
    assert_same_cloud(&expected, &back, "pcl_pcd2ply table");
    let ours = scratch("ours_table.ply");
    ply::write(&ours, &cloud, ply::Encoding::BinaryLittleEndian).unwrap();
    let via = scratch("ours_table_via_pcl.pcd");
    let mut cmd = pcl_tool("pcl_ply2pcd").unwrap();
    cmd.arg(&ours).arg(&via);
    run(cmd);
    assert_same_cloud(
        &cloud.clone(),
        &pcd::read(&via).unwrap(),
        "pcl_ply2pcd table",
    );
}

#[test]
fn writers_round_trip_real_clouds() {
    for file in [
        "bun0.pcd",
        "table_scene_mug_stereo_textured.pcd",
        "office1.pcd",
    ] {
        let cloud = pcd::read(&data(file)).unwrap();
        for enc in [
            Encoding::Ascii,
            Encoding::Binary,
            Encoding::BinaryCompressed,
        ] {
            let back = pcd::from_bytes(&pcd::to_bytes(&cloud, enc).unwrap()).unwrap();
            assert_same_cloud(&cloud, &back, &format!("{file} {enc:?}"));
        }
        for enc in [
            ply::Encoding::Ascii,
            ply::Encoding::BinaryLittleEndian,
            ply::Encoding::BinaryBigEndian,
        ] {
            let back = ply::from_bytes(&ply::to_bytes(&cloud, enc).unwrap()).unwrap();
            assert_same_cloud(&cloud, &back, &format!("{file} {enc:?}"));
        }
    }
    // Through files and the extension dispatch.
    let cloud = pcd::read(&data("bun0.pcd")).unwrap();
    for name in ["rt.pcd", "rt.ply"] {
        let path = scratch(name);
        io::write_cloud(&path, &cloud, Encoding::Binary).unwrap();
        assert_same_cloud(&cloud, &io::read_cloud(&path).unwrap(), name);
    }
}

/// PCL's grabber frames: the 16-bit TIFF depth image deprojects (fx = fy = 525, cx = 320,
/// cy = 240, 1 mm units) to the PCD of the same stamp, NaN exactly where the depth is 0.
#[test]
fn grabber_depth_frames_deproject_to_their_pcd() {
    let intrinsics = PinholeIntrinsics::PCL_GRABBER;
    let mut worst = 0.0f32;
    for stamp in GRABBER_STAMPS {
        let tiff = data(&format!("grabber_sequences/tiff/frame_{stamp}_depth.tiff"));
        let image = depth::read(&tiff, 0.001).unwrap();
        let cloud = image.deproject(&intrinsics).unwrap();
        let reference =
            pcd::read(&data(&format!("grabber_sequences/pcd/frame_{stamp}.pcd"))).unwrap();
        assert_eq!(
            (cloud.width, cloud.height),
            (reference.width, reference.height)
        );
        let mut compared = 0;
        for (i, (p, q)) in cloud.points.iter().zip(&reference.points).enumerate() {
            assert_eq!(
                p.is_finite(),
                q.is_finite(),
                "{stamp}: pixel {i}: {p} vs {q}"
            );
            if p.is_finite() {
                worst = worst.max((*p - *q).abs().max_element());
                compared += 1;
            }
        }
        assert!(compared > 200_000, "{stamp}: {compared} valid pixels");
        // The PNG writer round-trips the frame.
        let png = scratch(&format!("{stamp}.png"));
        depth::write(&png, &image).unwrap();
        assert_eq!(depth::read(&png, 0.001).unwrap(), image);
    }
    eprintln!("grabber frames: max |deprojected - PCD| = {worst:e} m");
    assert!(worst < 1e-5, "max deviation {worst} m");
}

#[test]
fn malformed_real_files_name_the_file_and_problem() {
    let bytes = std::fs::read(data("milk.pcd")).unwrap();
    let mut bad_type = bytes.clone();
    let at = bytes.windows(10).position(|w| w == b"TYPE F F F").unwrap();
    bad_type[at + 9] = b'Q';
    let cases: [(&str, Vec<u8>, &str); 3] = [
        (
            "truncated.pcd",
            bytes[..bytes.len() / 2].to_vec(),
            "truncated",
        ),
        ("header_only.pcd", bytes[..200].to_vec(), "truncated"),
        ("bad_type.pcd", bad_type, "unknown type"),
    ];
    for (name, contents, problem) in cases {
        let path = scratch(name);
        std::fs::write(&path, contents).unwrap();
        let err = pcd::read(&path).unwrap_err().to_string();
        assert!(err.contains(name) && err.contains(problem), "{err}");
    }
    let path = scratch("bad.tiff");
    std::fs::write(&path, &bytes[..100]).unwrap();
    let err = depth::read(&path, 0.001).unwrap_err().to_string();
    assert!(
        err.contains("bad.tiff") && err.contains("image codec"),
        "{err}"
    );
}

#[test]
fn convert_command_deprojects_a_depth_frame() {
    let stamp = GRABBER_STAMPS[0];
    let tiff = data(&format!("grabber_sequences/tiff/frame_{stamp}_depth.tiff"));
    let out = scratch("convert.pcd");
    let status = Command::new(env!("CARGO_BIN_EXE_hapcloud"))
        .arg("convert")
        .arg(&tiff)
        .arg(&out)
        .args([
            "--intrinsics",
            "525,525,320,240",
            "--format",
            "binary-compressed",
        ])
        .status()
        .unwrap();
    assert!(status.success());
    let intrinsics = PinholeIntrinsics::PCL_GRABBER;
    let expected = depth::read(&tiff, 0.001)
        .unwrap()
        .deproject(&intrinsics)
        .unwrap();
    assert_same_cloud(&pcd::read(&out).unwrap(), &expected, "convert");
    let failed = Command::new(env!("CARGO_BIN_EXE_hapcloud"))
        .arg("convert")
        .arg(&tiff)
        .arg(&out)
        .output()
        .unwrap();
    assert!(!failed.status.success());
    assert!(String::from_utf8_lossy(&failed.stderr).contains("needs --intrinsics"));
}
