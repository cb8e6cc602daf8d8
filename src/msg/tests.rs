//! Round trips of every message kind, zero-copy reads, and rejection of bad bytes without a panic.

use std::borrow::Cow;

use nalgebra::{UnitQuaternion, Vector3};

use super::*;
use crate::core::camera::{Camera, PinholeIntrinsics};
use crate::core::change::free_space::FreeSpaceCheck;
use crate::core::change::fusion::{FusedChange, FusionConfig};
use crate::core::change::{ChangeConfig, ChangeKind, ChangeRegion, ClassCounts};
use crate::core::frame::CoarseOutcome;
use crate::core::rigid::Rigid3;
use crate::core::verify::PoseHypothesis;

fn info() -> FrameInfo {
    FrameInfo {
        name: "DJI_0001.JPG".to_string(),
        camera_id: 2,
        camera: Camera::pinhole(4, 3, PinholeIntrinsics::centered(5.0, 4, 3)),
        intrinsics_known: true,
        initial_cam_from_world: Rigid3::new(
            UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3),
            Vector3::new(1.0, 2.0, -3.5),
        ),
        seed: 77,
    }
}

/// A coarse view's grid samples for [`info`]'s 4×3 camera at stride 2: two samples (row 1,
/// columns 1 and 3), one of them without a face.
fn grid() -> GridArrays<'static> {
    GridArrays {
        face_index: Cow::Owned(vec![17, u32::MAX]),
        depth_m: Cow::Owned(vec![41.5, 0.0]),
    }
}

fn header() -> Header {
    Header {
        frame_id: 9,
        sequence: 3,
        capture_time_ns: 1_700_000_000_000_000_000,
        sent_time_ns: 1_700_000_000_100_000_000,
    }
}

fn every_kind() -> Vec<Body<'static>> {
    let image: Vec<f32> = (0..12).map(|i| i as f32 / 12.0).collect();
    let outcome = CoarseOutcome {
        coarse_index: 4,
        consistent_matches: 321,
        hypothesis: Err("too few points".to_string()),
    };
    vec![
        Body::Frame(Frame {
            info: info(),
            image: Cow::Owned(image.clone()),
            depth_m: Cow::Owned(Vec::new()),
        }),
        Body::FlowJob(FlowJob {
            meta: FlowJobMeta {
                info: info(),
                coarse_index: 4,
                coarse_count: 15,
                coarse_cam_from_world: Rigid3::identity(),
                render_ms: 12.5,
            },
            query: Cow::Owned(image.clone()),
            asg: Cow::Owned(image.iter().map(|v| 1.0 - v).collect()),
            depth_m: Cow::Owned(vec![7.0; 12]),
            face_index: Cow::Owned((0..12).collect()),
        }),
        Body::Correspondences(Correspondences {
            meta: CorrespondencesMeta {
                info: info(),
                coarse_index: 4,
                coarse_count: 15,
                coarse_cam_from_world: Rigid3::identity(),
                render_ms: 1.0,
                flow_ms: 2.0,
                flow_worker: 1,
                grid_stride_px: 2,
            },
            image_points_px: Cow::Owned(vec![0.5, 1.5, 2.5, 3.5]),
            world_points_m: Cow::Owned(vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]),
            grid: grid(),
        }),
        Body::Hypothesis(Hypothesis {
            meta: HypothesisMeta {
                info: info(),
                coarse_count: 15,
                outcome,
                render_ms: 1.0,
                flow_ms: 2.0,
                pose_ms: 3.0,
                flow_worker: 0,
                grid_stride_px: 0,
            },
            grid: GridArrays::default(),
        }),
        Body::Hypothesis(Hypothesis {
            meta: HypothesisMeta {
                info: info(),
                coarse_count: 15,
                outcome: CoarseOutcome {
                    coarse_index: 5,
                    consistent_matches: 1234,
                    hypothesis: Ok(PoseHypothesis {
                        camera: info().camera,
                        cam_from_world: info().initial_cam_from_world,
                        consensus: 900,
                        inlier_rms_px: 0.75,
                        correspondence_count: 1100,
                        coarse_cam_from_world: Rigid3::identity(),
                    }),
                },
                render_ms: 1.0,
                flow_ms: 2.0,
                pose_ms: 3.0,
                flow_worker: 1,
                grid_stride_px: 2,
            },
            grid: grid(),
        }),
        Body::FrameFailed(FrameFailed {
            name: "a.png".to_string(),
            stage: "ingest".to_string(),
            reason: "truncated PNG".to_string(),
        }),
        Body::PoseResult(PoseResult {
            frame_id: 9,
            name: "a.png".to_string(),
            accepted: true,
            failure: None,
            confidence: 0.8,
            camera: Some(CameraNumbers::from(&info().camera)),
            cam_from_world: Some(PoseNumbers::from(&info().initial_cam_from_world)),
            evidence: Evidence {
                refinement: Some(RefinementNumbers {
                    verified_edge_support: 0.3,
                    aligned_edge_support: 0.5,
                    kept: true,
                }),
                ..Evidence::default()
            },
            times: StageTimesMs::default(),
            flow_workers: vec![0, 1, 0],
        }),
        Body::Credit(Credit {
            worker_index: 3,
            incarnation: 99,
            completed: vec![JobKey {
                frame_id: 1,
                coarse_index: 2,
            }],
            free_slots: 1,
        }),
        Body::Metrics(StageMetrics {
            stage: "flow".to_string(),
            compute_samples_ms: vec![1.0, 2.0],
            ..StageMetrics::default()
        }),
        Body::StreamEnd(StreamEnd {
            frame_count: 48,
            finished_frames: Vec::new(),
        }),
        Body::FrameQuery(FrameQuery {
            info: info(),
            query: Cow::Owned(image.clone()),
            depth_m: Cow::Owned(vec![12.5; 12]),
            photo: Cow::Owned(Vec::new()),
        }),
        Body::ChangeJob(ChangeJob {
            meta: ChangeJobMeta {
                info: info(),
                camera: info().camera,
                cam_from_world: info().initial_cam_from_world,
                neighbours: vec![NeighbourMeta {
                    frame_id: 3,
                    name: "view_003.png".to_string(),
                    camera: info().camera,
                    cam_from_world: info().initial_cam_from_world,
                }],
                pose_sigma_px: 1.25,
            },
            depth_m: Cow::Owned(Vec::new()),
            photo: Cow::Owned(image.clone()),
            neighbour_photos: Cow::Owned(image.iter().map(|v| 1.0 - v).collect()),
        }),
        Body::ChangeResult(change_result_example()),
        Body::ChangeSet(ChangeSet {
            complete: true,
            frame_count: Some(4),
            frames_with_result: 4,
            frames_with_map: 3,
            objects: vec![FusedChange {
                kind: ChangeKind::Added,
                frames: vec![0, 2],
                confirmed: true,
                footprint_m: vec![[0.0, 0.0], [4.0, 0.0], [4.0, 3.0]],
                footprint_area_m2: 6.0,
                height_m: 5.5,
                centroid_m: [1.0, 2.0, 3.0],
                confidence: 0.9,
                region_count: 2,
            }],
            fusion: FusionConfig::default(),
            free_space: vec![FreeSpaceCheck {
                object: 0,
                centroid_m: [1.0, 2.0, 3.0],
                seen_through_by: vec![1, 3, 4],
                agreed_by: vec![0, 2],
                refuted: true,
            }],
        }),
        Body::ChangeSight(ChangeSight {
            meta: ChangeSightMeta {
                result: change_result_example(),
                view: Some(SightView {
                    camera: info().camera,
                    cam_from_world: info().initial_cam_from_world,
                    config: ChangeConfig {
                        pose_sigma_px: 1.5,
                        quadratic_sigma_per_m: 0.002,
                        ..ChangeConfig::default()
                    },
                }),
            },
            photo_depth_m: Cow::Owned(image.iter().map(|v| 30.0 + v).collect()),
            model_depth_m: Cow::Owned(vec![42.0; 12]),
        }),
        Body::ChangeSight(ChangeSight {
            meta: ChangeSightMeta {
                result: ChangeResult {
                    failure: Some("no depth: stereo chose no neighbour".to_string()),
                    regions: Vec::new(),
                    ..change_result_example()
                },
                view: None,
            },
            photo_depth_m: Cow::Owned(Vec::new()),
            model_depth_m: Cow::Owned(Vec::new()),
        }),
        Body::PoseLender(PoseLender {
            meta: PoseLenderMeta {
                info: info(),
                camera: info().camera,
                cam_from_world: info().initial_cam_from_world,
                steps: 1,
            },
            query: Cow::Owned(image.clone()),
        }),
    ]
}

fn change_result_example() -> ChangeResult {
    ChangeResult {
        frame_id: 9,
        name: "a.png".to_string(),
        failure: None,
        counts: ClassCounts {
            unknown: 1,
            unchanged: 8,
            added: 2,
            removed: 1,
        },
        regions: vec![ChangeRegion {
            kind: ChangeKind::Added,
            pixel_count: 40,
            surface_area_m2: 20.0,
            footprint_area_m2: 12.0,
            height_m: 6.0,
            vertical_extent_m: 5.0,
            footprint_width_m: 3.0,
            footprint_length_m: 4.0,
            depth_difference_m: 5.5,
            centroid_m: [1.0, 2.0, 3.0],
            footprint_m: vec![[0.0, 0.0], [4.0, 0.0], [4.0, 3.0], [0.0, 3.0]],
            confidence: 0.8,
            bbox_px: [0, 0, 2, 2],
        }],
        change_ms: 3.5,
        change_worker: Some(1),
    }
}

#[test]
fn every_kind_round_trips() {
    for body in every_kind() {
        let message = Envelope {
            header: header(),
            body,
        };
        let bytes = encode(&message).unwrap().to_vec();
        assert_eq!(bytes.len() % 8, 0);
        assert_eq!(
            decode(&bytes).unwrap(),
            message,
            "{:?}",
            message.body.kind()
        );
    }
}

/// The bytes of every message kind are pinned by golden files (`tests/data/wire/v<N>/`): a change
/// to any struct that reaches the wire (a core type included) fails here, and must come with a
/// new schema version (`SCHEMA_VERSION`, `schemas/v<N>/`) and new golden files. To write them
/// for a new version: `ASGREG_WRITE_GOLDEN=1 cargo test --lib msg::tests::golden`.
#[test]
fn golden_bytes_of_every_kind() {
    let folder = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/wire")
        .join(format!("v{SCHEMA_VERSION}"));
    let write = std::env::var_os("ASGREG_WRITE_GOLDEN").is_some();
    let mut kinds_seen = std::collections::BTreeSet::new();
    for (index, body) in every_kind().into_iter().enumerate() {
        let kind = body.kind();
        kinds_seen.insert(kind as u16);
        let bytes = encode(&Envelope {
            header: header(),
            body,
        })
        .unwrap()
        .to_vec();
        let path = folder.join(format!("{index:02}_{kind:?}.bin"));
        if write {
            std::fs::create_dir_all(&folder).unwrap();
            std::fs::write(&path, &bytes).unwrap();
        }
        let golden = std::fs::read(&path).unwrap_or_else(|error| {
            panic!(
                "{}: {error}; golden files are part of the repository (see this test's comment)",
                path.display()
            )
        });
        assert!(
            golden == bytes,
            "{kind:?}: the encoded bytes differ from {} (schema v{SCHEMA_VERSION} changed: bump \
             SCHEMA_VERSION and write schemas/v<N+1>/ and new golden files)",
            path.display()
        );
    }
    let every_kind: Vec<u16> = (1..=15).collect();
    assert_eq!(
        kinds_seen.into_iter().collect::<Vec<_>>(),
        every_kind,
        "a golden file for every message kind"
    );
}

#[test]
fn aligned_arrays_are_read_in_place() {
    let message = Envelope {
        header: header(),
        body: every_kind().swap_remove(1),
    };
    let encoded = encode(&message).unwrap();
    // An 8-byte aligned buffer, as iceoryx2 and Vec<u64> give.
    let mut storage = vec![0u64; encoded.len() / 8];
    let bytes: &mut [u8] = bytemuck::cast_slice_mut(&mut storage);
    encoded.write_to(bytes);
    let decoded = decode(bytes).unwrap();
    let Body::FlowJob(job) = decoded.body else {
        panic!("wrong kind")
    };
    assert!(matches!(job.asg, Cow::Borrowed(_)));
    assert!(matches!(job.face_index, Cow::Borrowed(_)));
    let start = bytes.as_ptr() as usize;
    let asg = job.asg.as_ptr() as usize;
    assert!(
        asg > start && asg < start + bytes.len(),
        "the ASG must point into the message"
    );
}

#[test]
fn misaligned_bytes_are_copied_not_rejected() {
    let message = Envelope {
        header: header(),
        body: every_kind().swap_remove(2),
    };
    let bytes = encode(&message).unwrap().to_vec();
    let mut shifted = vec![0u8; bytes.len() + 1];
    shifted[1..].copy_from_slice(&bytes);
    assert_eq!(decode(&shifted[1..]).unwrap(), message);
}

#[test]
fn wrong_schema_version_names_both_versions() {
    let message = Envelope {
        header: header(),
        body: every_kind().swap_remove(0),
    };
    let mut bytes = encode(&message).unwrap().to_vec();
    let other = SCHEMA_VERSION + 1;
    bytes[4..6].copy_from_slice(&other.to_le_bytes());
    let error = decode(&bytes).unwrap_err();
    assert_eq!(
        error,
        DecodeError::WrongVersion {
            found: other,
            frame_id: 9
        }
    );
    let text = error.to_string();
    assert!(
        text.contains(&format!("schema version {other}"))
            && text.contains(&format!("version {SCHEMA_VERSION}")),
        "{text}"
    );
}

#[test]
fn bad_bytes_are_errors_never_panics() {
    assert!(matches!(
        decode(b"hello"),
        Err(DecodeError::TooShort { .. })
    ));
    assert!(matches!(
        decode(&[0u8; 64]),
        Err(DecodeError::BadMagic { .. })
    ));
    for body in every_kind() {
        let message = Envelope {
            header: header(),
            body,
        };
        let bytes = encode(&message).unwrap().to_vec();
        // Every truncation.
        for len in 0..bytes.len() {
            assert!(decode(&bytes[..len]).is_err() || len >= bytes.len() - 7);
        }
        // Every single-byte corruption of header and body: an error or a message, no panic.
        for position in 0..bytes.len().min(160) {
            let mut corrupt = bytes.clone();
            corrupt[position] ^= 0xA5;
            let _ = decode(&corrupt);
        }
    }
}

#[test]
fn array_sizes_are_checked_against_the_camera() {
    let message = Envelope {
        header: header(),
        body: Body::Frame(Frame {
            info: info(),
            image: Cow::Owned(vec![0.0; 11]),
            depth_m: Cow::Owned(Vec::new()),
        }),
    };
    let bytes = encode(&message).unwrap().to_vec();
    let error = decode(&bytes).unwrap_err().to_string();
    assert!(
        error.contains("'image' has 11 values, expected 12"),
        "{error}"
    );
}

/// A hypothesis' grid samples are as many as its camera's grid has at its stride (none at
/// stride 0), and read back as the core's samples.
#[test]
fn grid_samples_are_checked_against_the_camera_and_stride() {
    let Body::Hypothesis(hypothesis) = every_kind().swap_remove(4) else {
        panic!("the fifth example is the hypothesis with a pose");
    };
    let samples = hypothesis.grid_samples().unwrap();
    assert_eq!((samples.width_px(), samples.height_px()), (4, 3));
    assert_eq!(samples.stride_px(), 2);
    assert_eq!(samples.face_index(), &[17, u32::MAX]);
    assert_eq!(samples.depth_m(), &[41.5, 0.0]);
    let decode_error = |hypothesis: Hypothesis<'static>| {
        let bytes = encode(&Envelope {
            header: header(),
            body: Body::Hypothesis(hypothesis),
        })
        .unwrap()
        .to_vec();
        decode(&bytes).unwrap_err().to_string()
    };
    let mut one_short = hypothesis.clone();
    one_short.grid.depth_m = Cow::Owned(vec![41.5]);
    let error = decode_error(one_short);
    assert!(
        error.contains("'grid_depth_m' has 1 values, expected 2"),
        "{error}"
    );
    let mut other_stride = hypothesis.clone();
    other_stride.meta.grid_stride_px = 1;
    let error = decode_error(other_stride);
    assert!(
        error.contains("'grid_face_index' has 2 values, expected 12"),
        "{error}"
    );
    let mut no_stride = hypothesis;
    no_stride.meta.grid_stride_px = 0;
    assert!(no_stride.grid_samples().is_none());
    let error = decode_error(no_stride);
    assert!(
        error.contains("'grid_face_index' has 2 values, expected 0"),
        "{error}"
    );
}

fn pose_result_example() -> PoseResult {
    every_kind()
        .into_iter()
        .find_map(|body| match body {
            Body::PoseResult(result) => Some(result),
            _ => None,
        })
        .expect("every_kind has a PoseResult")
}

#[test]
fn pose_result_json_carries_header_and_result() {
    let result = pose_result_example();
    let json: serde_json::Value =
        serde_json::from_str(&pose_result_json(&header(), &result)).unwrap();
    assert_eq!(json["schema_version"], SCHEMA_VERSION);
    assert_eq!(json["frame_id"], 9);
    assert_eq!(json["accepted"], true);
    assert_eq!(
        json["cam_from_world"]["qvec_wxyz"]
            .as_array()
            .unwrap()
            .len(),
        4
    );
}

#[test]
fn pose_result_json_has_exactly_the_schema_properties() {
    let schema: serde_json::Value =
        serde_json::from_str(include_str!("../../schemas/v9/pose_result.schema.json")).unwrap();
    let keys = |value: &serde_json::Value| -> Vec<String> {
        let mut keys: Vec<String> = value.as_object().unwrap().keys().cloned().collect();
        keys.sort();
        keys
    };
    let result = pose_result_example();
    let json: serde_json::Value =
        serde_json::from_str(&pose_result_json(&header(), &result)).unwrap();
    let properties = &schema["properties"];
    assert_eq!(keys(&json), keys(properties));
    let mut required: Vec<String> = schema["required"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap().to_string())
        .collect();
    required.sort();
    assert_eq!(required, keys(properties));
    for nested in ["evidence", "times"] {
        assert_eq!(
            keys(&json[nested]),
            keys(&properties[nested]["properties"]),
            "{nested}"
        );
    }
    assert_eq!(
        keys(&json["camera"]),
        keys(&properties["camera"]["oneOf"][1]["properties"])
    );
    assert_eq!(
        keys(&json["cam_from_world"]),
        keys(&properties["cam_from_world"]["oneOf"][1]["properties"])
    );
}

fn sorted_keys(value: &serde_json::Value) -> Vec<String> {
    let mut keys: Vec<String> = value
        .as_object()
        .unwrap_or_else(|| panic!("not an object: {value}"))
        .keys()
        .cloned()
        .collect();
    keys.sort();
    keys
}

/// The JSON of `json` has exactly the schema's properties, every one required.
fn assert_matches_schema(json: &serde_json::Value, schema: &serde_json::Value) {
    let properties = &schema["properties"];
    assert_eq!(sorted_keys(json), sorted_keys(properties));
    let mut required: Vec<String> = schema["required"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap().to_string())
        .collect();
    required.sort();
    assert_eq!(required, sorted_keys(properties));
}

#[test]
fn change_result_json_has_exactly_the_schema_properties() {
    let schema: serde_json::Value =
        serde_json::from_str(include_str!("../../schemas/v9/change_result.schema.json")).unwrap();
    let json: serde_json::Value =
        serde_json::from_str(&change_result_json(&header(), &change_result_example())).unwrap();
    assert_eq!(json["schema_version"], SCHEMA_VERSION);
    assert_matches_schema(&json, &schema);
    let properties = &schema["properties"];
    assert_eq!(
        sorted_keys(&json["counts"]),
        sorted_keys(&properties["counts"]["properties"])
    );
    assert_eq!(
        sorted_keys(&json["regions"][0]),
        sorted_keys(&properties["regions"]["items"]["properties"])
    );
}

#[test]
fn change_set_json_has_exactly_the_schema_properties() {
    let schema: serde_json::Value =
        serde_json::from_str(include_str!("../../schemas/v9/change_set.schema.json")).unwrap();
    let set = every_kind()
        .into_iter()
        .find_map(|body| match body {
            Body::ChangeSet(set) => Some(set),
            _ => None,
        })
        .expect("every_kind has a ChangeSet");
    let json: serde_json::Value = serde_json::from_str(&change_set_json(&header(), &set)).unwrap();
    assert_matches_schema(&json, &schema);
    let properties = &schema["properties"];
    assert_eq!(
        sorted_keys(&json["objects"][0]),
        sorted_keys(&properties["objects"]["items"]["properties"])
    );
    assert_eq!(
        sorted_keys(&json["fusion"]),
        sorted_keys(&properties["fusion"]["properties"])
    );
    assert_eq!(
        sorted_keys(&json["free_space"][0]),
        sorted_keys(&properties["free_space"]["items"]["properties"])
    );
}

/// A change worker's ChangeSight carries the depths of its camera's size, or none without a
/// change map; any other length is an error naming the array.
#[test]
fn a_change_sight_carries_both_depths_of_its_camera_or_none() {
    let sights: Vec<ChangeSight> = every_kind()
        .into_iter()
        .filter_map(|body| match body {
            Body::ChangeSight(sight) => Some(sight),
            _ => None,
        })
        .collect();
    let (photo, model) = sights[0].depths().unwrap().expect("a change map");
    assert_eq!((photo.size(), model.size()), ((4, 3), (4, 3)));
    assert_eq!(sights[1].depths().unwrap(), None);
    let mut short = sights[0].clone();
    short.model_depth_m = Cow::Owned(vec![1.0; 11]);
    let bytes = encode(&Envelope {
        header: header(),
        body: Body::ChangeSight(short),
    })
    .unwrap()
    .to_vec();
    let error = decode(&bytes).unwrap_err().to_string();
    assert!(
        error.contains("'model_depth_m' has 11 values, expected 12"),
        "{error}"
    );
}
