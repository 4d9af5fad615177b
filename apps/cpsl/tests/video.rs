//! `cpsl layer-video` end to end on a short clip, and its errors.

mod common;
use common::{cpsl, fails, ok, s, test_clip};

#[test]
fn layers_a_clip_and_refuses_bad_input() {
    if !common::fastdepth_present() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let clip = dir.path().join("clip.mp4");
    test_clip(&clip, &["-bf", "0"]);
    let out = dir.path().join("layers");
    let msg = ok(&[
        "layer-video",
        s(&clip),
        "-o",
        s(&out),
        "--gop",
        "4",
        "--layers",
        "4",
    ]);
    assert!(msg.contains("wrote 7 frames"), "{msg}");
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("video.json")).unwrap()).unwrap();
    let frames = v["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 7);
    assert_eq!(frames[0]["kind"], "I");
    assert_eq!(frames[4]["kind"], "I", "GOP 4");
    assert!(frames.iter().any(|f| f["motion"] == "decoder"));
    for f in frames {
        assert!(out
            .join(f["dir"].as_str().unwrap())
            .join("manifest.json")
            .is_file());
    }
    // Rendering a frame works like any layer set.
    ok(&[
        "render",
        s(&out.join("frame_000003")),
        "--pose",
        "0.02,0,0,0,0,0",
        "-o",
        s(&dir.path().join("v.png")),
    ]);
    // Running again replaces its own output.
    ok(&["layer-video", s(&clip), "-o", s(&out), "--max-frames", "2"]);
    // The folder renders like a package: any frame, a frame past the end refused.
    let view = dir.path().join("f1.png");
    let pose = "0.02,0,0,0,0,0";
    let args = ["render", s(&out), "--pose", pose, "-o", s(&view)];
    ok(&[&args[..], &["--frame", "1"]].concat());
    assert!(view.is_file());
    fails(&[&args[..], &["--frame", "2"]].concat(), "has 2 frames");
    // `cpsl encode` codes the folder as it was layered: the same package as encoding the clip
    // with the same options, byte for byte.
    let from_layers = dir.path().join("from_layers.cpsl");
    let direct = dir.path().join("direct.cpsl");
    let q = ["--quality", "30"];
    ok(&[&["encode", s(&out), "-o", s(&from_layers)], &q[..]].concat());
    ok(&[
        &["encode", s(&clip), "-o", s(&direct), "--max-frames", "2"],
        &q[..],
    ]
    .concat());
    let coded = files(&from_layers);
    assert!(
        !coded.is_empty() && coded == files(&direct),
        "the packages differ"
    );
    // Layering cpsl's own output is refused with what to do instead.
    let again = dir.path().join("again");
    fails(&["layer-video", s(&out), "-o", s(&again)], "layered video");
    let frame = out.join("frame_000000");
    fails(&["encode", s(&frame), "-o", s(&direct)], "is a layer set");
    // `cpsl info` summarises the output.
    let info = ok(&["info", s(&out)]);
    for part in [
        "cpsl-video-layers",
        "2 frames (1 I, 1 P)",
        "I-frames: 0 (first)",
        "first frame",
    ] {
        assert!(info.contains(part), "{info} lacks {part}");
    }
    // `cpsl verify` reads every frame, and names each damaged one.
    assert!(ok(&["verify", s(&out)]).contains("ok (2 frames checked)"));
    let png = out.join("frame_000001").join("layer_00.png");
    let bytes = std::fs::read(&png).unwrap();
    std::fs::write(&png, &bytes[..bytes.len() / 2]).unwrap();
    let o = cpsl(&["verify", s(&out)]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{err}");
    assert!(
        err.contains("frame_000001/layer_00.png") && err.contains("1 of 2 frames"),
        "{err}"
    );
    // Bad input: clear errors, nothing written.
    let junk = dir.path().join("junk.mp4");
    std::fs::write(&junk, b"not a video").unwrap();
    let empty = dir.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    let other = dir.path().join("other");
    std::fs::create_dir(&other).unwrap();
    std::fs::write(other.join("keep.txt"), "mine").unwrap();
    for (input, output, expect) in [
        (
            dir.path().join("missing.mp4"),
            dir.path().join("o1"),
            "cannot read",
        ),
        (junk.clone(), dir.path().join("o2"), "cannot read"),
        (empty.clone(), dir.path().join("o3"), "no frames"),
        (clip.clone(), other.clone(), "not replacing"),
    ] {
        let o = cpsl(&["layer-video", s(&input), "-o", s(&output)]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && err.contains(expect),
            "{input:?}: {err}"
        );
        assert!(output == other || !output.exists(), "{output:?} written");
        let leftovers: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .filter_map(|e| e.ok())
            .filter(|e| e.file_name().to_string_lossy().ends_with(".partial"))
            .collect();
        assert!(leftovers.is_empty(), "staging left behind: {leftovers:?}");
    }
    assert_eq!(
        std::fs::read_to_string(other.join("keep.txt")).unwrap(),
        "mine"
    );
}

#[test]
fn a_damaged_packet_costs_its_frame_only() {
    if !common::fastdepth_present() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let clip = dir.path().join("clip.mp4");
    test_clip(&clip, &["-bf", "0"]);
    // The fourth picture's first NAL unit claims 2 GB: the decoder refuses that packet.
    let probe = std::process::Command::new("ffprobe")
        .args([
            "-v",
            "error",
            "-select_streams",
            "v",
            "-show_entries",
            "packet=pos",
        ])
        .args(["-of", "csv=p=0", s(&clip)])
        .output()
        .expect("the ffprobe tool (scripts/setup-system.sh)");
    let pos: Vec<usize> = String::from_utf8_lossy(&probe.stdout)
        .lines()
        .map(|l| l.trim().parse().unwrap())
        .collect();
    let mut bytes = std::fs::read(&clip).unwrap();
    bytes[pos[3]..pos[3] + 4].copy_from_slice(&[0x7f, 0xff, 0xff, 0xff]);
    let damaged = dir.path().join("damaged.mp4");
    std::fs::write(&damaged, bytes).unwrap();
    let out = dir.path().join("layers");
    let o = cpsl(&["layer-video", s(&damaged), "-o", s(&out), "--layers", "3"]);
    let (msg, err) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert!(o.status.success(), "{err}");
    assert!(msg.contains("wrote 6 frames"), "{msg}");
    assert!(err.contains("1 damaged packet(s) skipped"), "{err}");
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("video.json")).unwrap()).unwrap();
    assert_eq!(v["damaged_packets"], 1);
}

/// Every file under `dir` (relative path and bytes), in path order.
fn files(dir: &std::path::Path) -> Vec<(std::path::PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                todo.push(p);
            } else {
                let bytes = std::fs::read(&p).unwrap();
                out.push((p.strip_prefix(dir).unwrap().to_path_buf(), bytes));
            }
        }
    }
    out.sort();
    out
}
