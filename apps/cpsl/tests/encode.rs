//! `cpsl encode`, `info`, `verify` and `render` of a package, end to end on a short clip.

mod common;
use common::{cpsl, ok, s, test_clip};

#[test]
fn encodes_verifies_and_renders_a_package() {
    if !common::fastdepth_present() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let clip = dir.path().join("clip.mp4");
    test_clip(&clip, &[]);
    let pkg = dir.path().join("clip.cpsl");
    let args = [
        "encode",
        s(&clip),
        "-o",
        s(&pkg),
        "--gop",
        "4",
        "--layers",
        "4",
    ];
    let msg = ok(&[&args[..], &["--bitrate", "2M"]].concat());
    assert!(msg.contains("7 frames, 2 segments"), "{msg}");
    let info = ok(&["info", s(&pkg)]);
    assert!(info.contains("192x128") && info.contains("h264"), "{info}");
    assert!(ok(&["verify", s(&pkg)]).contains("ok"));
    // Render a frame of the package from a new viewpoint.
    let png = dir.path().join("view.png");
    ok(&[
        "render",
        s(&pkg),
        "--frame",
        "5",
        "--pose",
        "0.05,0,0,0,0,0",
        "-o",
        s(&png),
    ]);
    assert!(png.is_file());
    let o = cpsl(&[
        "render",
        s(&pkg),
        "--frame",
        "7",
        "--pose",
        "0,0,0,0,0,0",
        "-o",
        s(&png),
    ]);
    assert!(!o.status.success(), "frame 7 of 7 must be refused");
    // A sweep longer than the package plays it frame by frame, back to its first segment.
    let sweep = dir.path().join("sweep");
    ok(&[
        "render",
        s(&pkg),
        "--sweep",
        "tx:-0.05:0.05:9",
        "-o",
        s(&sweep),
    ]);
    assert!(sweep.join("frame_008.png").is_file());
    // Playback benchmark: 9 frames of 7 loop over both segments into the first again.
    let report = ok(&["bench", "play", s(&pkg), "--frames", "9", "--json"]);
    let v: serde_json::Value = serde_json::from_str(&report).unwrap();
    assert_eq!(
        (v["frames"].as_u64(), v["layers"].as_u64()),
        (Some(9), Some(4))
    );
    assert!(v["fps"].as_f64().unwrap() > 0.0 && v["decode"]["median_ms"].as_f64().unwrap() > 0.0);
    // A damaged segment fails verification with the file named.
    let side = pkg.join("seg_000001/side.bin");
    let mut bytes = std::fs::read(&side).unwrap();
    bytes[50] ^= 0xff;
    std::fs::write(&side, &bytes).unwrap();
    let o = cpsl(&["verify", s(&pkg)]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("side.bin"));
    // Re-encoding replaces the package; a folder that is not a package is never replaced.
    ok(&[&args[..], &["--codec", "vp9", "--quality", "40"]].concat());
    assert!(ok(&["info", s(&pkg)]).contains("vp9"));
    assert!(ok(&["verify", s(&pkg)]).contains("ok"));
    let other = dir.path().join("keep");
    std::fs::create_dir(&other).unwrap();
    std::fs::write(other.join("mine.txt"), "x").unwrap();
    let o = cpsl(&["encode", s(&clip), "-o", s(&other)]);
    assert!(!o.status.success());
    assert!(other.join("mine.txt").is_file());
    // Bad arguments are refused clearly.
    let o = cpsl(&["encode", s(&clip), "-o", s(&pkg), "--bitrate", "lots"]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("not a bitrate"));
    let o = cpsl(&["encode", s(&clip), "-o", s(&pkg), "--quality", "99"]);
    assert!(!o.status.success());
    let o = cpsl(&["info", s(&dir.path().join("nothing"))]);
    assert!(!o.status.success());
    // The single-file form: written by encode --archive or pack, read by every command.
    let archive = dir.path().join("clip_one.cpsl");
    let msg = ok(&[
        "encode",
        s(&clip),
        "-o",
        s(&archive),
        "--archive",
        "--gop",
        "4",
        "--layers",
        "4",
    ]);
    assert!(msg.contains("7 frames, 2 segments"), "{msg}");
    assert!(archive.is_file());
    assert!(ok(&["info", s(&archive)]).contains("192x128"));
    assert!(ok(&["verify", s(&archive)]).contains("ok"));
    ok(&[
        "render",
        s(&archive),
        "--frame",
        "5",
        "--pose",
        "0.05,0,0,0,0,0",
        "-o",
        s(&png),
    ]);
    let packed = dir.path().join("packed.cpsl");
    assert!(ok(&["pack", s(&pkg), "-o", s(&packed)]).contains("wrote"));
    assert!(ok(&["verify", s(&packed)]).contains("ok"));
    // An archive never replaces a folder, nor a folder an archive.
    assert!(!cpsl(&["encode", s(&clip), "-o", s(&pkg), "--archive"])
        .status
        .success());
    assert!(!cpsl(&["encode", s(&clip), "-o", s(&archive)])
        .status
        .success());
    assert!(archive.is_file() && pkg.is_dir());
    // No staging folder is left behind.
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| {
            let n = e.file_name().to_string_lossy().into_owned();
            n.ends_with(".partial") || n.ends_with(".folder")
        })
        .collect();
    assert!(left.is_empty());
}
