//! The CAN protocol of `hapcloud::io::can` against its DBC file, candump logs and a socket.
//!
//! - typed values survive encode -> decode within one LSB (property test);
//! - `hapcloud.dbc` parses with `can-dbc`, and decoding logged frames with the DBC's own
//!   signal definitions (start bit, length, byte order, sign, factor, offset) gives back the
//!   values sent, signal by signal;
//! - frames sent through `socketcan::CanSocket` over a Unix datagram socket pair (no vcan on
//!   these machines: the crate wraps any fd, and a CAN_RAW socket carries exactly these
//!   16-byte `struct can_frame` datagrams) decode to the values sent.

use hapcloud::io::can::{
    self, CanBackend, CanConstraint, CanJointState, CanKeepOff, CanSender, CanStatus, CanSurface,
    CanTorqueCommand, CanValue, CandumpWriter, Decoder, encode,
};
use proptest::prelude::*;

mod common;
use socketcan::{CanSocket, Socket};
use std::collections::HashMap;

fn arb_value() -> impl Strategy<Value = CanValue> {
    let torque = (
        prop::array::uniform6(-327.0f64..327.0),
        any::<bool>(),
        any::<u8>(),
    )
        .prop_map(|(torques_nm, enabled, counter)| {
            CanValue::TorqueCommand(CanTorqueCommand {
                torques_nm,
                enabled,
                counter,
            })
        });
    let joints = (
        prop::array::uniform6(-3.2f64..3.2),
        prop::array::uniform6(-32.0f64..32.0),
    )
        .prop_map(|(positions_rad, velocities_rad_s)| {
            CanValue::JointState(CanJointState {
                positions_rad,
                velocities_rad_s,
            })
        });
    let constraint = (
        prop::array::uniform3(-3.2f64..3.2),
        prop::array::uniform4(any::<bool>()),
        any::<u8>(),
    )
        .prop_map(|([d, p, v], flags, counter)| {
            CanValue::Constraint(CanConstraint {
                d_proj_m: d,
                alpha_p_m: p,
                alpha_v_m_s: v,
                position_active: flags[0],
                velocity_active: flags[1],
                force_active: flags[2],
                surface_valid: flags[3],
                counter,
            })
        });
    let keep_off = (
        prop::array::uniform3(-3.2f64..3.2),
        0u8..8,
        0u8..3,
        prop::array::uniform3(any::<bool>()),
        any::<u8>(),
    )
        .prop_map(|([d, rate, p], guard_index, status, flags, counter)| {
            CanValue::KeepOff(CanKeepOff {
                d_proj_m: d,
                d_rate_m_s: rate,
                alpha_p_m: p,
                guard_index,
                status,
                position_active: flags[0],
                blind_guard: flags[1],
                held: flags[2],
                counter,
            })
        });
    let surface = (
        0u8..16,
        0u8..16,
        prop::array::uniform3(-3.2f64..3.2),
        prop::array::uniform3(-1.0f64..1.0),
        0.0f64..1.0,
        any::<bool>(),
    )
        .prop_map(|(camera_id, counter, centroid_m, normal, quality, valid)| {
            CanValue::Surface(CanSurface {
                camera_id,
                counter,
                centroid_m,
                normal,
                quality,
                valid,
            })
        });
    let status = (
        0u32..65536,
        any::<u16>(),
        any::<bool>(),
        0.0f64..6500.0,
        any::<u8>(),
    )
        .prop_map(
            |(deadline_misses, fault_flags, gpu, latency_ms, heartbeat)| {
                CanValue::Status(CanStatus {
                    deadline_misses,
                    fault_flags,
                    backend: if gpu {
                        CanBackend::Gpu
                    } else {
                        CanBackend::Cpu
                    },
                    latency_ms,
                    heartbeat,
                })
            },
        );
    prop_oneof![torque, joints, constraint, keep_off, surface, status]
}

/// Every signal of a value by its DBC name, with the resolution (LSB) the protocol gives it.
fn expected_signals(value: &CanValue) -> Vec<(String, f64, f64)> {
    let b = |v: bool| f64::from(u8::from(v));
    let mut out: Vec<(String, f64, f64)> = Vec::new();
    match value {
        CanValue::TorqueCommand(v) => {
            for (j, t) in v.torques_nm.iter().enumerate() {
                out.push((format!("Joint{}Torque", j + 1), *t, 0.01));
            }
            out.push(("TorqueEnable".into(), b(v.enabled), 1.0));
            out.push(("TorqueCounter".into(), f64::from(v.counter), 1.0));
        }
        CanValue::JointState(v) => {
            for j in 0..6 {
                out.push((format!("Joint{}Position", j + 1), v.positions_rad[j], 1e-4));
                out.push((
                    format!("Joint{}Velocity", j + 1),
                    v.velocities_rad_s[j],
                    1e-3,
                ));
            }
        }
        CanValue::Constraint(v) => {
            out.push(("DProj".into(), v.d_proj_m, 1e-4));
            out.push(("AlphaP".into(), v.alpha_p_m, 1e-4));
            out.push(("AlphaV".into(), v.alpha_v_m_s, 1e-4));
            out.push(("PositionActive".into(), b(v.position_active), 1.0));
            out.push(("VelocityActive".into(), b(v.velocity_active), 1.0));
            out.push(("ForceActive".into(), b(v.force_active), 1.0));
            out.push(("SurfaceValid".into(), b(v.surface_valid), 1.0));
            out.push(("ConstraintCounter".into(), f64::from(v.counter), 1.0));
        }
        CanValue::KeepOff(v) => {
            out.push(("GuardDProj".into(), v.d_proj_m, 1e-4));
            out.push(("GuardDRate".into(), v.d_rate_m_s, 1e-4));
            out.push(("GuardAlphaP".into(), v.alpha_p_m, 1e-4));
            out.push(("GuardIndex".into(), f64::from(v.guard_index), 1.0));
            out.push(("GuardStatus".into(), f64::from(v.status), 1.0));
            out.push(("GuardPositionActive".into(), b(v.position_active), 1.0));
            out.push(("GuardBlind".into(), b(v.blind_guard), 1.0));
            out.push(("GuardHeld".into(), b(v.held), 1.0));
            out.push(("GuardCounter".into(), f64::from(v.counter), 1.0));
        }
        CanValue::Surface(v) => {
            for (k, axis) in ["X", "Y", "Z"].iter().enumerate() {
                out.push((format!("Centroid{axis}"), v.centroid_m[k], 1e-4));
                out.push((format!("Normal{axis}"), v.normal[k], 1e-4));
            }
            for prefix in ["Centroid", "Normal"] {
                out.push((format!("{prefix}CameraId"), f64::from(v.camera_id), 1.0));
                out.push((format!("{prefix}Counter"), f64::from(v.counter), 1.0));
            }
            out.push(("Quality".into(), v.quality, 0.01));
            out.push(("EstimateValid".into(), b(v.valid), 1.0));
        }
        CanValue::Status(v) => {
            out.push(("DeadlineMisses".into(), f64::from(v.deadline_misses), 1.0));
            out.push(("FaultFlags".into(), f64::from(v.fault_flags), 1.0));
            out.push(("Backend".into(), f64::from(v.backend as u8), 1.0));
            out.push(("LatencyMs".into(), v.latency_ms, 0.1));
            out.push(("Heartbeat".into(), f64::from(v.heartbeat), 1.0));
        }
    }
    out
}

/// `a` and `b` agree within one LSB of each signal.
fn assert_close(sent: &CanValue, back: &CanValue) {
    let got: HashMap<String, f64> = expected_signals(back)
        .into_iter()
        .map(|(n, v, _)| (n, v))
        .collect();
    for (name, value, lsb) in expected_signals(sent) {
        let diff = (got[&name] - value).abs();
        assert!(
            diff <= lsb,
            "{name}: sent {value}, got {} (lsb {lsb})",
            got[&name]
        );
    }
}

fn decode_all(frames: &[socketcan::CanFrame]) -> Vec<CanValue> {
    let mut decoder = Decoder::new();
    let values = frames
        .iter()
        .filter_map(|f| decoder.push(f).unwrap())
        .collect();
    assert_eq!(decoder.incomplete, 0);
    values
}

proptest! {
    #[test]
    fn encode_decode_round_trips_within_one_lsb(value in arb_value()) {
        let encoded = encode(&value);
        prop_assert!(!encoded.saturated);
        let back = decode_all(&encoded.frames);
        prop_assert_eq!(back.len(), 1);
        assert_close(&value, &back[0]);
    }

    /// Logged frames decoded with the DBC's signal definitions give back the values sent.
    #[test]
    fn candump_log_decodes_with_the_dbc(values in prop::collection::vec(arb_value(), 1..12)) {
        let dbc = can::parse_dbc(can::DBC_TEXT).unwrap();
        let mut log = CandumpWriter::new(Vec::new(), "can0");
        for (i, value) in values.iter().enumerate() {
            log.write_value(1_700_000_000.0 + i as f64 * 0.00125, value).unwrap();
        }
        let text = log.into_inner();
        let logged = can::read_candump(text.as_slice()).unwrap();
        let mut at = 0;
        for value in &values {
            let expected = expected_signals(value);
            let mut seen = 0;
            for _ in 0..encode(value).frames.len() {
                let (_, signals) = can::decode_with_dbc(&dbc, &logged[at].frame).unwrap();
                for (name, got) in signals {
                    let (_, sent, lsb) = expected.iter().find(|(n, ..)| n == name).unwrap();
                    prop_assert!((got - sent).abs() <= *lsb, "{}: sent {}, got {}", name, sent, got);
                    seen += 1;
                }
                at += 1;
            }
            prop_assert_eq!(seen, expected.len());
        }
        prop_assert_eq!(at, logged.len());
        // The typed decoder reads the same log back.
        let frames: Vec<_> = logged.iter().map(|l| l.frame).collect();
        let back = decode_all(&frames);
        prop_assert_eq!(back.len(), values.len());
        for (sent, got) in values.iter().zip(&back) {
            assert_close(sent, got);
        }
    }
}

#[test]
fn dbc_describes_exactly_the_protocol() {
    let dbc = can::parse_dbc(can::DBC_TEXT).unwrap();
    let mut ids: Vec<u32> = dbc.messages.iter().map(|m| m.id.raw()).collect();
    ids.sort();
    let protocol = [
        can::id::TORQUE_COMMAND_1_4,
        can::id::TORQUE_COMMAND_5_6,
        can::id::JOINT_STATE_1_2,
        can::id::JOINT_STATE_3_4,
        can::id::JOINT_STATE_5_6,
        can::id::HAPTIC_CONSTRAINT,
        can::id::KEEP_OFF_GUARD,
        can::id::SURFACE_CENTROID,
        can::id::SURFACE_NORMAL,
        can::id::NODE_STATUS,
    ];
    assert_eq!(ids, protocol.map(u32::from).to_vec());
    for message in &dbc.messages {
        assert_eq!(message.size, 8, "{}", message.name);
        // No two signals of a message overlap, and all fit in 64 bits.
        let mut used = 0u64;
        for s in &message.signals {
            assert!(s.start_bit + s.size <= 64, "{}", s.name);
            let bits = if s.size == 64 {
                u64::MAX
            } else {
                ((1u64 << s.size) - 1) << s.start_bit
            };
            assert_eq!(used & bits, 0, "{} overlaps", s.name);
            used |= bits;
        }
    }
    let backend = dbc
        .signal_by_name(
            can_dbc::MessageId::Standard(can::id::NODE_STATUS),
            "Backend",
        )
        .unwrap();
    assert_eq!(backend.size, 2);
}

#[test]
fn candump_lines_have_the_can_utils_format() {
    let mut log = CandumpWriter::new(Vec::new(), "can0");
    let status = CanValue::Status(CanStatus {
        deadline_misses: 3,
        fault_flags: can::fault::CAMERA_STALE | can::fault::GPU_FALLBACK,
        backend: CanBackend::Gpu,
        latency_ms: 41.7,
        heartbeat: 0xAB,
    });
    log.write_value(1_700_000_000.25, &status).unwrap();
    let text = String::from_utf8(log.into_inner()).unwrap();
    // DeadlineMisses 3, FaultFlags 3, Backend 1, LatencyMs 417 = 0x01A1, Heartbeat 0xAB.
    assert_eq!(text, "(1700000000.250000) can0 140#0300030001A101AB\n");
    let err = can::read_candump("(1700000000.25) can0 140#00\n".as_bytes()).unwrap_err();
    assert!(err.to_string().contains("line 1"), "{err}");
}

#[test]
fn sender_writes_can_frames_through_a_socket_pair() {
    let (ours, theirs) = std::os::unix::net::UnixDatagram::pair().unwrap();
    let tx = CanSocket::from(std::os::fd::OwnedFd::from(ours));
    let rx = CanSocket::from(std::os::fd::OwnedFd::from(theirs));
    let mut sender = CanSender::from_socket(tx, "socketpair").unwrap();
    let values = [
        CanValue::TorqueCommand(CanTorqueCommand {
            torques_nm: [1.5, -2.25, 30.0, -40.0, 0.01, 0.0],
            enabled: true,
            counter: 9,
        }),
        CanValue::Surface(CanSurface {
            camera_id: 1,
            counter: 15,
            centroid_m: [0.4, -0.1, 1.2],
            normal: [0.0, -0.6, 0.8],
            quality: 0.93,
            valid: true,
        }),
        CanValue::JointState(CanJointState {
            positions_rad: [0.1, 0.2, -0.3, 1.4, -1.5, 3.0],
            velocities_rad_s: [0.0, 1.0, -2.0, 3.0, -4.0, 15.0],
        }),
    ];
    let mut count = 0;
    for v in &values {
        count += sender.send(v).unwrap().frames.len();
    }
    assert_eq!(sender.frames_sent, count as u64);
    assert_eq!(sender.frames_dropped, 0);
    let mut frames = Vec::new();
    for _ in 0..count {
        frames.push(rx.read_frame().unwrap());
    }
    let back = decode_all(&frames);
    assert_eq!(back.len(), values.len());
    for (sent, got) in values.iter().zip(&back) {
        assert_close(sent, got);
    }
    // With the receiver gone, sending reports a socket error instead of blocking.
    drop(rx);
    assert!(sender.send(&values[0]).is_err());
}

#[test]
fn opening_a_missing_interface_names_it() {
    let err = CanSender::open("hapcloud_no_such_can9").unwrap_err();
    assert!(err.to_string().contains("hapcloud_no_such_can9"), "{err}");
}

#[test]
fn can_decode_command_reads_a_log() {
    let dir = common::TempDir::new("can_protocol");
    let path = dir.path.join("node.log");
    let mut log = CandumpWriter::new(std::fs::File::create(&path).unwrap(), "can0");
    let constraint = CanConstraint {
        d_proj_m: 0.0421,
        alpha_p_m: -0.0032,
        alpha_v_m_s: 0.25,
        position_active: true,
        velocity_active: true,
        force_active: false,
        surface_valid: true,
        counter: 7,
    };
    log.write_value(1_700_000_000.0, &CanValue::Constraint(constraint))
        .unwrap();
    // The nearest keep-off guard (the elbow, index 1), 12.3 mm off its surface and closing.
    let guard = CanKeepOff {
        d_proj_m: 0.0123,
        d_rate_m_s: -0.25,
        alpha_p_m: 0.0021,
        guard_index: 1,
        status: 0,
        position_active: true,
        blind_guard: true,
        held: false,
        counter: 7,
    };
    log.write_value(1_700_000_000.001, &CanValue::KeepOff(guard))
        .unwrap();
    log.flush().unwrap();
    let out = common::run_ok(["can-decode".as_ref(), "--json".as_ref(), path.as_os_str()]);
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(json["frames"], 2);
    assert_eq!(json["unknown"], 0);
    let message = &json["messages"][0];
    assert_eq!(message["name"], "HapticConstraint");
    let d_proj = message["signals"]["DProj"].as_f64().unwrap();
    assert!((d_proj - 0.0421).abs() <= 1e-4, "{d_proj}");
    assert_eq!(message["signals"]["ConstraintCounter"], 7.0);
    let message = &json["messages"][1];
    assert_eq!(message["name"], "KeepOffGuard");
    let signals = &message["signals"];
    let d_proj = signals["GuardDProj"].as_f64().unwrap();
    assert!((d_proj - 0.0123).abs() <= 1e-4, "{d_proj}");
    let rate = signals["GuardDRate"].as_f64().unwrap();
    assert!((rate + 0.25).abs() <= 1e-4, "{rate}");
    for (name, v) in [
        ("GuardIndex", 1.0),
        ("GuardStatus", 0.0),
        ("GuardPositionActive", 1.0),
        ("GuardBlind", 1.0),
        ("GuardHeld", 0.0),
        ("GuardCounter", 7.0),
    ] {
        assert_eq!(signals[name], v, "{name}: {message}");
    }
    // The text output names the message and its signals.
    let out = common::run_ok(["can-decode".as_ref(), path.as_os_str()]);
    let text = String::from_utf8(out.stdout).unwrap();
    let line = text.lines().nth(1).unwrap();
    assert!(
        line.contains("121 KeepOffGuard") && line.contains("GuardIndex=1"),
        "{text}"
    );
}
