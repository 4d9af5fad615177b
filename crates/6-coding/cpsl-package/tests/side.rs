//! Side streams and manifests: round trips, and every damaged or truncated input is an error,
//! never a panic.

use cpsl_core::{Camera, Edc, EdcSample, Geometry, RefreshReason, Vec3};
use cpsl_package::*;

fn side(slanted: bool) -> SideStream {
    let edc = |n: u16| Edc {
        width: 64,
        height: 48,
        layers: 2,
        step: 0.01,
        samples: (0..n)
            .map(|i| EdcSample {
                x: i % 64,
                y: i / 64,
                front: 0,
                back: 1,
                front_offset: -3,
                back_offset: 5,
            })
            .collect(),
    };
    let layer = |stream, depth| SideLayer {
        stream,
        depth,
        geometry: if slanted && stream == 1 {
            Geometry::Slanted(Vec3::new(0.0, 0.125, 0.25))
        } else {
            Geometry::Plane
        },
        confidence: 0.75,
        track: Some(stream as u32 + 10),
    };
    SideStream {
        segment: 2,
        start: 30,
        streams: 2,
        width: 64,
        height: 48,
        frames: (0..3)
            .map(|i| SideFrame {
                index: 30 + i,
                intra: i == 0,
                refresh: (i == 0).then_some(RefreshReason::Confidence),
                layers: vec![layer(0, 1.5), layer(1, 4.0 + i as f32)],
                edc: edc(100 + i as u16),
            })
            .collect(),
    }
}

#[test]
fn side_stream_round_trips_and_rejects_damage() {
    for slanted in [false, true] {
        round_trip_and_damage(side(slanted));
    }
}

#[test]
fn fronto_parallel_segments_stay_version_1() {
    let version = |s: SideStream| u16::from_le_bytes(s.encode()[8..10].try_into().unwrap());
    assert_eq!(version(side(false)), 1);
    assert_eq!(version(side(true)), 2);
}

/// A mesh grid on the side stream's quantisation lattice (as every decoded grid is).
fn grid(w: u32, h: u32, step: u32, shift: i32) -> std::sync::Arc<cpsl_core::DepthGrid> {
    let (cols, rows) = cpsl_core::DepthGrid::dims(w, h, step);
    std::sync::Arc::new(cpsl_core::DepthGrid {
        step,
        cols,
        rows,
        inverse_depth: (0..cols * rows)
            .map(|k| {
                let q = -700 + (k % cols) as i32 * 3 + (k / cols) as i32 + shift;
                (q as f64 * GRID_STEP).exp() as f32
            })
            .collect(),
    })
}

#[test]
fn mesh_grids_round_trip_predicted_from_the_previous_record() {
    let mut s = side(true);
    for (i, f) in s.frames.iter_mut().enumerate() {
        // Frame 2's grid differs from frame 1's in one place only.
        let g = grid(64, 48, 8, (i == 0) as i32);
        let g = if i == 2 {
            let mut v = (*g).clone();
            v.inverse_depth[5] *= 1.5f32;
            v.inverse_depth[5] = ((v.inverse_depth[5] as f64).ln() / GRID_STEP).round() as f32;
            v.inverse_depth[5] = (v.inverse_depth[5] as f64 * GRID_STEP).exp() as f32;
            std::sync::Arc::new(v)
        } else {
            g
        };
        f.layers[0].geometry = Geometry::Mesh(g);
    }
    round_trip_and_damage(s.clone());
    // Predicted from the previous record, the P-frames' grids cost less than coded alone.
    let alone: usize = s
        .frames
        .iter()
        .map(|f| {
            SideStream {
                frames: vec![f.clone()],
                ..s.clone()
            }
            .encode()
            .len()
        })
        .sum();
    assert!(
        s.encode().len() + 2 * 40 < alone,
        "{} vs {alone}",
        s.encode().len()
    );
    // A grid of the wrong size for the frame is an error naming the layer.
    let mut bad = side(true);
    bad.frames[0].layers[0].geometry = Geometry::Mesh(grid(64, 40, 8, 0));
    let e = SideStream::decode(&bad.encode()).unwrap_err().to_string();
    assert!(e.contains("layer 0: mesh grid"), "{e}");
}

#[test]
fn non_finite_planes_are_rejected() {
    let mut s = side(true);
    s.frames[1].layers[1].geometry = Geometry::Slanted(Vec3::new(f64::NAN, 0.0, 0.25));
    let e = SideStream::decode(&s.encode()).unwrap_err().to_string();
    assert!(
        e.contains("record 1") && e.contains("layer 1: geometry"),
        "{e}"
    );
}

fn round_trip_and_damage(s: SideStream) {
    let bytes = s.encode();
    assert_eq!(SideStream::decode(&bytes).unwrap(), s);
    // The compact EDC is far below 8 bytes per sample.
    assert!(bytes.len() < 3 * 100 * 3, "{} bytes", bytes.len());
    for cut in 0..bytes.len() {
        assert!(
            SideStream::decode(&bytes[..cut]).is_err(),
            "truncated at {cut}"
        );
    }
    for at in 0..bytes.len() {
        let mut bad = bytes.clone();
        bad[at] ^= 0x01;
        assert!(SideStream::decode(&bad).is_err(), "flipped bit at {at}");
    }
    let mut longer = bytes.clone();
    longer.push(0);
    assert!(SideStream::decode(&longer).is_err());
}

fn manifest() -> PackageManifest {
    let file = |p: &str| FileEntry {
        path: p.into(),
        bytes: 10,
        sha256: "ab".repeat(32),
    };
    PackageManifest {
        format: PACKAGE_FORMAT.into(),
        version: PACKAGE_VERSION,
        camera: Camera::from_fov(64, 48, 60.0),
        frame_rate: 30.0,
        frames: 5,
        layers: 4,
        codec: Codec::Vp9,
        layout: Layout {
            kind: "colour-over-alpha".into(),
            coded_width: 64,
            coded_height: 48,
            pixel_format: "yuv420p".into(),
            matrix: "bt709".into(),
            range: "limited".into(),
        },
        budget: Some(3_000_000),
        inits: vec![file("init_64x96.mp4")],
        depth: vec![DepthRun {
            first: 0,
            last: 4,
            note: "video: 81 % of pixels from 4 views".into(),
        }],
        segments: vec![Segment {
            start: 0,
            frames: 5,
            streams: vec![StreamEntry {
                file: None,
                init: Some("init_64x96.mp4".into()),
                track: Some(1),
                bitrate: 1000,
                quality: 30.0,
                scale: 2,
                weight: 1.5,
            }],
            fragment: Some(file("seg_000000/layers.m4s")),
            side: file("seg_000000/side.bin"),
        }],
        checksum: String::new(),
    }
}

/// [`manifest`] as a version 5 package (a fragment file per stream).
fn manifest_v5() -> PackageManifest {
    let mut m = manifest();
    m.version = 5;
    let mut f = m.segments[0].fragment.take().unwrap();
    f.path = "seg_000000/layer_00.m4s".into();
    m.segments[0].streams[0].file = Some(f);
    m
}

/// [`manifest`] as a version 3 package (self-contained MP4 streams, no init segments).
fn manifest_v3() -> PackageManifest {
    let mut m = manifest_v5();
    m.version = 3;
    m.inits.clear();
    m.depth.clear();
    m.segments[0].streams[0].init = None;
    m.segments[0].streams[0].file.as_mut().unwrap().path = "seg_000000/layer_00.mp4".into();
    m
}

#[test]
fn version_6_segments_share_one_fragment() {
    let err = |m: PackageManifest| {
        PackageManifest::parse(&m.to_json())
            .unwrap_err()
            .to_string()
    };
    assert!(PackageManifest::parse(&manifest_v5().to_json()).is_ok());
    let files: Vec<String> = manifest().files().map(|f| f.path.clone()).collect();
    assert_eq!(
        files,
        [
            "init_64x96.mp4",
            "seg_000000/layers.m4s",
            "seg_000000/side.bin"
        ]
    );
    let mut m = manifest();
    m.segments[0].fragment = None;
    assert!(err(m).contains("segments[0].fragment`: missing"));
    let mut m = manifest();
    m.segments[0].streams[0].file = manifest_v5().segments[0].streams[0].file.clone();
    assert!(err(m).contains("segments[0].streams[0].file`: a version 6 stream"));
    // Before version 6 every stream has its file and no segment a fragment.
    let mut m = manifest_v5();
    m.segments[0].fragment = manifest().segments[0].fragment.clone();
    assert!(err(m).contains("version 5 segments have none"));
    let mut m = manifest_v5();
    m.segments[0].streams[0].file = None;
    assert!(err(m).contains("segments[0].streams[0].file`: missing"));
    // The fragment's path is checked like any file's.
    let mut m = manifest();
    m.segments[0].fragment.as_mut().unwrap().path = "../x.m4s".into();
    assert!(err(m).contains("segments[0]"));
}

#[test]
fn version_4_streams_name_a_listed_init_segment() {
    assert!(PackageManifest::parse(&manifest().to_json()).is_ok());
    assert!(PackageManifest::parse(&manifest_v3().to_json()).is_ok());
    let err = |m: PackageManifest| {
        PackageManifest::parse(&m.to_json())
            .unwrap_err()
            .to_string()
    };
    let mut m = manifest();
    m.segments[0].streams[0].init = None;
    assert!(err(m).contains("streams[0].init`: missing"));
    let mut m = manifest();
    m.segments[0].streams[0].init = Some("init_2x2.mp4".into());
    assert!(err(m).contains("is not one of the manifest's `inits`"));
    let mut m = manifest();
    m.inits[0].path = "../init.mp4".into();
    assert!(err(m).contains("inits[0].path"));
    let mut m = manifest();
    m.inits.push(m.inits[0].clone());
    assert!(err(m).contains("used twice"));
    // Older versions have none.
    let mut m = manifest_v3();
    m.segments[0].streams[0].init = Some("init_64x96.mp4".into());
    assert!(err(m).contains("version 3 streams have no init segment"));
    let mut m = manifest_v3();
    m.inits = manifest().inits;
    assert!(err(m).contains("version 3 packages have no init segments"));
    // The init segments are files of the package.
    assert_eq!(manifest().files().next().unwrap().path, "init_64x96.mp4");
    assert_eq!(manifest().payload_bytes(), 20);
}

#[test]
fn depth_notes_are_checked() {
    let err = |m: PackageManifest| {
        PackageManifest::parse(&m.to_json())
            .unwrap_err()
            .to_string()
    };
    let back = PackageManifest::parse(&manifest().to_json()).unwrap();
    assert_eq!(back.depth, manifest().depth);
    assert!(!back.depth[0].is_fallback());
    // Version 5 brings them: a version 4 package with notes is refused, one without is read.
    let mut m = manifest_v5();
    m.version = 4;
    assert!(err(m.clone()).contains("version 4 packages have no depth notes"));
    m.depth.clear();
    assert!(PackageManifest::parse(&m.to_json()).is_ok());
    let run = |first, last, note: &str| DepthRun {
        first,
        last,
        note: note.into(),
    };
    for (runs, why) in [
        (vec![run(0, 5, "x")], "within the 5 frames"),
        (vec![run(3, 2, "x")], "in order"),
        (vec![run(0, 2, "x"), run(2, 4, "y")], "apart"),
        (vec![run(0, 4, "")], "printable text"),
        (vec![run(0, 4, "a\nb")], "printable text"),
        (
            vec![run(0, 4, &"x".repeat(MAX_DEPTH_NOTE + 1))],
            "printable text",
        ),
    ] {
        let mut m = manifest();
        m.depth = runs;
        let e = err(m);
        assert!(e.contains("`depth[") && e.contains(why), "{e}");
    }
}

#[test]
fn manifest_round_trips_and_checks_itself() {
    let m = manifest();
    let bytes = m.to_json();
    let back = PackageManifest::parse(&bytes).unwrap();
    assert_eq!(back.segments, m.segments);
    // Any changed byte (outside insignificant whitespace) is caught.
    let text = String::from_utf8(bytes.clone()).unwrap();
    for (at, c) in text.char_indices() {
        if c.is_whitespace() {
            continue;
        }
        let mut bad = bytes.clone();
        bad[at] ^= 0x01;
        assert!(PackageManifest::parse(&bad).is_err(), "flip at {at} ({c})");
    }
    // Unsafe paths and inconsistent segments are refused even with a valid checksum.
    for path in [
        "../x.mp4",
        "/abs.mp4",
        "a//b",
        "seg/%2e%2e",
        "manifest.json",
    ] {
        let mut m = manifest();
        m.segments[0].fragment.as_mut().unwrap().path = path.into();
        assert!(PackageManifest::parse(&m.to_json()).is_err(), "{path}");
        let mut m = manifest_v5();
        m.segments[0].streams[0].file.as_mut().unwrap().path = path.into();
        assert!(PackageManifest::parse(&m.to_json()).is_err(), "{path}");
    }
    let mut m2 = manifest();
    m2.frames = 6;
    assert!(PackageManifest::parse(&m2.to_json()).is_err());
    let mut m4 = manifest();
    m4.segments[0].streams[0].scale = 3;
    let e = PackageManifest::parse(&m4.to_json())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("scale") && e.contains("not one of 1, 2, 4, 8"),
        "{e}"
    );
    // Eighth size needs version 3; packages without it are written as version 2.
    let mut m7 = manifest_v3();
    m7.segments[0].streams[0].scale = 8;
    assert!(PackageManifest::parse(&m7.to_json()).is_ok());
    m7.version = 2;
    let e = PackageManifest::parse(&m7.to_json())
        .unwrap_err()
        .to_string();
    assert!(e.contains("not one of 1, 2, 4 (version 2"), "{e}");
    assert_eq!(cpsl_package::version_for([1, 2, 4, 2]), 2);
    assert_eq!(cpsl_package::version_for([1, 8]), 3);
    assert_eq!(cpsl_package::version_for([1, 1]), 2);
    // Version 1 manifests (no `scale`) still read, every stream at full size.
    let mut m5 = manifest_v3();
    m5.version = 1;
    m5.segments[0].streams[0].scale = 1;
    let v1 = m5.to_json();
    assert!(!String::from_utf8_lossy(&v1).contains("scale"));
    assert_eq!(
        PackageManifest::parse(&v1).unwrap().segments[0].streams[0].scale,
        1
    );
    // A version 1 manifest cannot carry a downscaled stream.
    let mut m6 = manifest_v3();
    m6.version = 1;
    let e = PackageManifest::parse(&m6.to_json())
        .unwrap_err()
        .to_string();
    assert!(e.contains("version 1"), "{e}");
    let mut m3 = manifest();
    m3.version = 99;
    assert!(matches!(
        PackageManifest::parse(&m3.to_json()),
        Err(PackageManifestError::Version(99))
    ));
}

#[test]
fn summarised_edc_keeps_every_pair_and_its_means() {
    let mut samples = Vec::new();
    for i in 0..1000u16 {
        samples.push(EdcSample {
            x: i % 64,
            y: i / 64 % 48,
            front: 0,
            back: 1,
            front_offset: (i % 7) as i8 - 3 + (i % 2) as i8,
            back_offset: 4,
        });
    }
    for i in 0..5u16 {
        samples.push(EdcSample {
            x: i,
            y: 47,
            front: 1,
            back: 2,
            front_offset: -(i as i8),
            back_offset: 2,
        });
    }
    samples.sort_by_key(|s| (s.y, s.x));
    let edc = Edc {
        width: 64,
        height: 48,
        layers: 3,
        step: 0.01,
        samples,
    };
    let s = summarise_edc(&edc);
    assert_eq!(s.samples.len(), 2, "one sample per pair");
    let (step, layers) = (s.step, s.layers);
    assert_eq!((step, layers), (0.01, 3));
    for (front, back) in [(0u8, 1u8), (1, 2)] {
        let of = |e: &Edc, side: fn(&EdcSample) -> i8| {
            let v: Vec<f64> = e
                .samples
                .iter()
                .filter(|s| (s.front, s.back) == (front, back))
                .map(|s| side(s) as f64)
                .collect();
            v.iter().sum::<f64>() / v.len() as f64
        };
        for side in [
            |s: &EdcSample| s.front_offset,
            |s: &EdcSample| s.back_offset,
        ] {
            let (full, summary) = (of(&edc, side), of(&s, side));
            assert!(
                (full - summary).abs() <= 0.5,
                "pair {front}-{back}: {full} vs {summary}"
            );
        }
    }
    // The summary survives the side stream's compact coding.
    assert_eq!(summarise_edc(&s), s);
}
