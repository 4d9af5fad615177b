//! Decoding real files written by the `ffmpeg` command line tool, and image sequences.

use cpsl_media::{open, open_ahead, open_with, FrameSource, MediaError};
use std::path::Path;
use std::process::Command;

/// Writes `frames` frames of FFmpeg's moving test pattern with the given encoder arguments.
fn encode(dir: &Path, name: &str, frames: usize, args: &[&str]) -> std::path::PathBuf {
    encode_from("testsrc2=size=160x120:rate=10", dir, name, frames, args)
}

/// Writes `frames` frames of the lavfi `source` with the given encoder arguments.
fn encode_from(
    source: &str,
    dir: &Path,
    name: &str,
    frames: usize,
    args: &[&str],
) -> std::path::PathBuf {
    let out = dir.join(name);
    let status = Command::new("ffmpeg")
        .args(["-v", "error", "-y", "-f", "lavfi", "-i", source])
        .args(["-frames:v", &frames.to_string()])
        .args(args)
        .arg(&out)
        .status()
        .expect("the ffmpeg tool (apt install ffmpeg; .ci/run installs it)");
    assert!(status.success());
    out
}

fn drain(src: &mut dyn FrameSource) -> Result<Vec<cpsl_media::InputFrame>, MediaError> {
    let mut v = Vec::new();
    while let Some(f) = src.next_frame()? {
        v.push(f);
    }
    Ok(v)
}

/// H.264 whose P-frames are predicted from the previous frame only (no B-frames, one
/// reference): its decoder vectors describe the motion.
const H264_WITH_MOTION: &[&str] = &[
    "-c:v", "libx264", "-bf", "0", "-refs", "1", "-pix_fmt", "yuv420p",
];

#[test]
fn decodes_h264_with_motion_vectors_and_vp9() {
    let dir = tempfile::tempdir().unwrap();
    let h264 = encode(dir.path(), "clip.mp4", 12, H264_WITH_MOTION);
    let mut src = open(&h264).unwrap();
    assert_eq!((src.info().width, src.info().height), (160, 120));
    assert!((src.info().fps - 10.0).abs() < 1e-6);
    let frames = drain(src.as_mut()).unwrap();
    assert_eq!(frames.len(), 12);
    assert!(frames.iter().all(|f| f.rgb.len() == 160 * 120 * 3));
    assert!(frames[0].motion.is_none(), "the first frame is intra");
    let with = frames.iter().filter(|f| f.motion.is_some()).count();
    assert!(with >= 8, "{with} P-frames carry motion vectors");
    // The pattern scrolls: some vectors are not zero.
    let m = frames.iter().find_map(|f| f.motion.as_ref()).unwrap();
    assert!(m.data.iter().any(|&v| v.abs() >= 1.0));
    // Without them where not asked for, and the same pictures.
    let bare = drain(open_with(&h264, false).unwrap().as_mut()).unwrap();
    assert_eq!(bare.len(), 12);
    assert!(bare.iter().all(|f| f.motion.is_none()));
    assert!(bare.iter().zip(&frames).all(|(a, b)| a.rgb == b.rgb));

    let vp9 = encode(
        dir.path(),
        "clip.webm",
        5,
        &["-c:v", "libvpx-vp9", "-deadline", "realtime"],
    );
    let mut src = open(&vp9).unwrap();
    let frames = drain(src.as_mut()).unwrap();
    assert_eq!(frames.len(), 5);
    assert!(frames.iter().all(|f| f.motion.is_none()));
}

/// H.264 at x264's defaults (three B-frames: a P-frame refers four frames back, B-frames to
/// later frames too) of a texture scrolling 2 pixels a frame: every frame's vectors, whatever
/// their reference, come out as the motion to the previous frame.
#[test]
fn motion_vectors_of_b_frames_and_far_references_are_per_frame() {
    let dir = tempfile::tempdir().unwrap();
    let scroll = "color=c=gray:s=160x120:r=10,noise=alls=100:allf=0,gblur=sigma=1.2,\
                  scroll=horizontal=0.0125";
    let x264 = ["-c:v", "libx264", "-pix_fmt", "yuv420p"];
    let clip = encode_from(scroll, dir.path(), "scroll.mp4", 12, &x264);
    let frames = drain(open(&clip).unwrap().as_mut()).unwrap();
    let mut with = 0;
    for (i, f) in frames.iter().enumerate() {
        let Some(m) = &f.motion else { continue };
        with += 1;
        // The median over the frame's inner part (the pattern wraps round at the edges).
        let mut u: Vec<f32> = (20..100)
            .flat_map(|y| (20..140).map(move |x| (x, y)))
            .map(|(x, y)| m.at(x, y).0)
            .collect();
        let mid = u.len() / 2;
        let u = *u.select_nth_unstable_by(mid, f32::total_cmp).1;
        assert!((u - 2.0).abs() < 0.5, "frame {i}: {u} pixels a frame");
    }
    assert!(with >= 8, "{with} frames with motion");
}

#[test]
fn bad_files_give_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    assert!(matches!(
        open(&dir.path().join("missing.mp4")),
        Err(MediaError::Unreadable { .. })
    ));
    let junk = dir.path().join("junk.mp4");
    std::fs::write(&junk, b"this is not a video").unwrap();
    assert!(matches!(open(&junk), Err(MediaError::Unreadable { .. })));
    // Audio only: no video stream.
    let audio = dir.path().join("tone.wav");
    let status = Command::new("ffmpeg")
        .args([
            "-v",
            "error",
            "-y",
            "-f",
            "lavfi",
            "-i",
            "sine=duration=0.2",
        ])
        .arg(&audio)
        .status()
        .unwrap();
    assert!(status.success());
    assert!(matches!(open(&audio), Err(MediaError::NoVideo(_))));
    // Truncated: whatever decodes comes out, then a clean end or a clear error; no panic.
    let clip = encode(
        dir.path(),
        "whole.mkv",
        20,
        &["-c:v", "libx264", "-pix_fmt", "yuv420p"],
    );
    let bytes = std::fs::read(&clip).unwrap();
    let cut = dir.path().join("cut.mkv");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    match open(&cut) {
        Ok(mut src) => match drain(src.as_mut()) {
            Ok(frames) => assert!(
                frames.len() < 20,
                "{} frames from half a file",
                frames.len()
            ),
            Err(e) => assert!(matches!(e, MediaError::Decode { .. }), "{e}"),
        },
        Err(e) => assert!(matches!(e, MediaError::Unreadable { .. }), "{e}"),
    }
}

#[test]
fn image_sequences_in_name_order_with_size_checks() {
    let dir = tempfile::tempdir().unwrap();
    assert!(matches!(open(dir.path()), Err(MediaError::Empty(_))));
    let png = |name: &str, w: u32, h: u32, v: u8| {
        let data = vec![v; (w * h * 3) as usize];
        cpsl_io::images::write_png(&dir.path().join(name), w, h, 3, &data).unwrap();
    };
    png("b_002.png", 8, 6, 20);
    png("a_001.png", 8, 6, 10);
    std::fs::write(dir.path().join("notes.txt"), "ignored").unwrap();
    let mut src = open(dir.path()).unwrap();
    assert_eq!(src.info().frames, Some(2));
    let frames = drain(src.as_mut()).unwrap();
    assert_eq!(frames[0].rgb[0], 10);
    assert_eq!(frames[1].rgb[0], 20);
    png("c_003.png", 4, 4, 30);
    let mut src = open(dir.path()).unwrap();
    assert!(matches!(
        drain(src.as_mut()),
        Err(MediaError::FrameSize { .. })
    ));
}

/// Runs the `ffmpeg` tool.
fn ffmpeg(args: &[&str]) {
    let status = Command::new("ffmpeg")
        .args(["-v", "error", "-y"])
        .args(args)
        .status()
        .expect("the ffmpeg tool");
    assert!(status.success(), "ffmpeg {args:?}");
}

#[test]
fn colour_follows_the_declared_matrix_and_range() {
    let dir = tempfile::tempdir().unwrap();
    // (200, 50, 20) flat, coded with a matrix and range and tagged with them (`None`: coded
    // untagged, as the ffmpeg tool does by default: BT.601, limited), then extra arguments.
    let cases = [
        ("bt709", Some(("bt709", "bt709", "tv")), &[][..]),
        ("bt601", Some(("bt601", "smpte170m", "tv")), &[]),
        ("bt2020", Some(("bt2020", "bt2020nc", "tv")), &[]),
        ("bt709-full", Some(("bt709", "bt709", "pc")), &[]),
        (
            "bt709-vp9",
            Some(("bt709", "bt709", "tv")),
            &["-c:v", "libvpx-vp9"],
        ),
        ("untagged", None, &[]),
    ];
    for (name, tags, extra) in cases {
        let ext = if name.ends_with("vp9") { "webm" } else { "mp4" };
        let path = dir.path().join(format!("{name}.{ext}"));
        let mut a: Vec<String> = ["-f", "lavfi", "-i", "color=c=0xC83214:s=64x48:r=10"]
            .into_iter()
            .map(String::from)
            .collect();
        a.extend(["-frames:v".into(), "2".into()]);
        match tags {
            Some((matrix, space, range)) => {
                let fmt = if range == "pc" { "yuvj420p" } else { "yuv420p" };
                let vf = format!("scale=out_color_matrix={matrix}:out_range={range},format={fmt}");
                for s in ["-vf", &vf, "-colorspace", space, "-color_range", range] {
                    a.push(s.into());
                }
            }
            None => a.extend(["-pix_fmt".into(), "yuv420p".into()]),
        }
        a.extend(extra.iter().map(|s| s.to_string()));
        a.push(path.to_str().unwrap().into());
        ffmpeg(&a.iter().map(String::as_str).collect::<Vec<_>>());
        let mut src = open(&path).unwrap();
        assert_eq!(src.info().hdr, None, "{name}");
        let f = src.next_frame().unwrap().unwrap();
        let px = &f.rgb[(24 * 64 + 32) * 3..][..3];
        for (got, want) in px.iter().zip([200u8, 50, 20]) {
            assert!(got.abs_diff(want) <= 3, "{name}: {px:?} for [200, 50, 20]");
        }
    }
}

/// Decodes a whole file to RGB with the `ffmpeg` tool (which turns pictures upright).
fn ffmpeg_rgb(path: &Path) -> Vec<u8> {
    let out = Command::new("ffmpeg")
        .args(["-v", "error", "-i"])
        .arg(path)
        .args(["-f", "rawvideo", "-pix_fmt", "rgb24", "-"])
        .output()
        .expect("the ffmpeg tool");
    assert!(out.status.success());
    out.stdout
}

#[test]
fn pictures_and_motion_turn_with_the_display_matrix() {
    let dir = tempfile::tempdir().unwrap();
    let plain = encode(dir.path(), "plain.mp4", 6, H264_WITH_MOTION);
    let upright = drain(open(&plain).unwrap().as_mut()).unwrap();
    let upright_rgb = |turn: u32| -> Vec<u8> {
        upright
            .iter()
            .flat_map(|f| cpsl_media::rotate(f.rgb.clone(), 160, 120, 3, turn))
            .collect()
    };
    let mean_diff = |a: &[u8], b: &[u8]| {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(a, b)| a.abs_diff(*b) as f64)
            .sum::<f64>()
            / a.len() as f64
    };
    for rotate in ["90", "180", "270"] {
        let path = dir.path().join(format!("r{rotate}.mp4"));
        let meta = format!("rotate={rotate}");
        ffmpeg(&[
            "-i",
            plain.to_str().unwrap(),
            "-c",
            "copy",
            "-metadata:s:v:0",
            &meta,
            path.to_str().unwrap(),
        ]);
        let mut src = open(&path).unwrap();
        let info = src.info().clone();
        let size = if info.rotation == 180 {
            (160, 120)
        } else {
            (120, 160)
        };
        assert!(info.rotation != 0, "rotate={rotate}: no rotation read");
        assert_eq!((info.width, info.height), size, "rotate={rotate}");
        let frames = drain(src.as_mut()).unwrap();
        // Our upright pictures, turned.
        let ours: Vec<u8> = frames.iter().flat_map(|f| f.rgb.clone()).collect();
        assert_eq!(ours, upright_rgb(info.rotation), "rotate={rotate}");
        // Turned as the ffmpeg tool shows the file: of the turns giving this size, ours is
        // the nearest to the tool's pictures (which differ from ours by their chroma
        // upsampling: nearest samples, about 5 levels on this pattern).
        let tool = ffmpeg_rgb(&path);
        let d = mean_diff(&ours, &tool);
        assert!(d < 8.0, "rotate={rotate}: {d} levels from the tool");
        for other in [0, 90, 180, 270] {
            if other != info.rotation && (other % 180 == info.rotation % 180) {
                let o = mean_diff(&upright_rgb(other), &tool);
                assert!(
                    o > 3.0 * d,
                    "rotate={rotate}: a turn of {other} is {o} from the tool, ours {d}"
                );
            }
        }
        // Motion turns with the picture: the field of the upright decode, rotated.
        for (f, u) in frames.iter().zip(&upright) {
            assert_eq!(
                f.motion,
                u.motion
                    .clone()
                    .map(|m| cpsl_media::rotate_motion(m, info.rotation))
            );
        }
        assert!(frames.iter().any(|f| f.motion.is_some()));
    }
}

/// Codes two frames from `inputs` (ffmpeg arguments) as 10-bit H.265 (losslessly where asked)
/// tagged HDR with the transfer `trc` and BT.2020 primaries, and reads the first back,
/// checking that it is reported as HDR (`name`).
fn first_hdr_frame(
    dir: &Path,
    inputs: &[&str],
    lossless: bool,
    trc: &str,
    name: &str,
) -> cpsl_media::InputFrame {
    let path = dir.join(format!("{name}.mp4"));
    let mut a = inputs.to_vec();
    a.extend([
        "-frames:v",
        "2",
        "-c:v",
        "libx265",
        "-x265-params",
        if lossless {
            "log-level=error:lossless=1"
        } else {
            "log-level=error"
        },
    ]);
    a.extend([
        "-color_trc",
        trc,
        "-color_primaries",
        "bt2020",
        "-colorspace",
        "bt2020nc",
    ]);
    a.extend(["-color_range", "tv", path.to_str().unwrap()]);
    ffmpeg(&a);
    let mut src = open(&path).unwrap();
    assert_eq!(src.info().hdr, Some(name));
    src.next_frame().unwrap().unwrap()
}

#[test]
fn hdr_video_is_mapped_to_sdr() {
    let dir = tempfile::tempdir().unwrap();
    let at =
        |f: &cpsl_media::InputFrame, i: usize| <[u8; 3]>::try_from(&f.rgb[i * 3..][..3]).unwrap();
    // PQ: (200, 50, 20) beside grey 128, SDR BT.709 turned into HDR10 by zimg with SDR white
    // at 203 cd/m2 (ITU-R BT.2408), coded 10-bit as Y'CbCr 4:2:0 and as R'G'B': they come back.
    let graph = "[0][1]hstack,format=gbrpf32le,zscale=tin=bt709:pin=bt709:min=gbr:rin=pc:\
                 t=smpte2084:p=bt2020:npl=203:";
    for coded in [
        "m=bt2020nc:r=tv,format=yuv420p10le",
        "m=gbr:r=pc,format=gbrp10le",
    ] {
        let graph = format!("{graph}{coded}");
        let inputs = [
            "-f",
            "lavfi",
            "-i",
            "color=c=0xC83214:s=64x48:r=10",
            "-f",
            "lavfi",
            "-i",
            "color=c=0x808080:s=64x48:r=10",
            "-filter_complex",
            &graph,
        ];
        let f = first_hdr_frame(dir.path(), &inputs, false, "smpte2084", "PQ");
        for (i, want) in [(24 * 128 + 32, [200u8, 50, 20]), (24 * 128 + 96, [128; 3])] {
            let px = at(&f, i);
            for (g, w) in px.iter().zip(want) {
                assert!(g.abs_diff(w) <= 4, "PQ {coded}: {px:?} for {want:?}");
            }
        }
    }
    // HLG: grey at 75 % of the signal is reference white (203 cd/m2 on the 1000 cd/m2
    // reference display): near SDR white, below it only by the highlight roll-off.
    let inputs = [
        "-f",
        "lavfi",
        "-i",
        "color=c=0xBFBFBF:s=64x48:r=10",
        "-vf",
        "scale=out_color_matrix=bt2020:out_range=tv,format=yuv420p10le",
    ];
    let px = at(
        &first_hdr_frame(dir.path(), &inputs, false, "arib-std-b67", "HLG"),
        24 * 64 + 32,
    );
    assert!(
        px.iter().all(|&c| (236..=250).contains(&c)) && px[0] == px[2],
        "HLG white: {px:?}"
    );
}

#[test]
fn hdr_gradients_keep_their_steps() {
    // A 10-bit PQ ramp from black to reference white (luma 64 to 572, 203 cd/m2), one code
    // every 2 pixels, coded losslessly. Through 8 bits before the mapping it would come back
    // with 113 of its 242 levels, in steps of up to 8 (bands); with 16 bits each step moves
    // the SDR picture by at most a level or two, and never down.
    let dir = tempfile::tempdir().unwrap();
    let inputs = [
        "-f",
        "lavfi",
        "-i",
        "color=black:s=1024x16:r=10,format=yuv420p10le,geq=lum='64+X/2':cb=512:cr=512",
    ];
    let f = first_hdr_frame(dir.path(), &inputs, true, "smpte2084", "PQ");
    let row: Vec<u8> = f.rgb[8 * 1024 * 3..][..1024 * 3]
        .iter()
        .step_by(3)
        .copied()
        .collect();
    let steps: Vec<i32> = row.windows(2).map(|p| p[1] as i32 - p[0] as i32).collect();
    let largest = *steps.iter().max().unwrap();
    assert!(steps.iter().all(|&d| d >= 0), "{row:?}");
    assert!(largest <= 2, "a step of {largest} levels: {row:?}");
    assert!(
        row[0] <= 1 && row[1023] >= 200,
        "{} .. {}",
        row[0],
        row[1023]
    );
}

#[test]
fn a_size_change_mid_stream_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let part = |name: &str, size: &str| {
        let p = dir.path().join(name);
        let src = format!("testsrc2=size={size}:rate=10");
        ffmpeg(&[
            "-f",
            "lavfi",
            "-i",
            &src,
            "-frames:v",
            "3",
            "-c:v",
            "libx264",
            "-pix_fmt",
            "yuv420p",
            "-f",
            "mpegts",
            p.to_str().unwrap(),
        ]);
        std::fs::read(p).unwrap()
    };
    // MPEG-TS segments concatenated byte by byte, as a live stream that changes size.
    let joined = dir.path().join("joined.ts");
    std::fs::write(
        &joined,
        [part("a.ts", "160x120"), part("b.ts", "96x64")].concat(),
    )
    .unwrap();
    let mut src = open(&joined).unwrap();
    let err = drain(src.as_mut()).unwrap_err();
    assert!(
        matches!(&err, MediaError::Decode { frames: 3, reason, .. } if reason.contains("mid-stream")),
        "{err}"
    );
    // Read ahead: the same three frames, then the same error.
    let mut ahead = open_ahead(&joined, true, 2).unwrap();
    for _ in 0..3 {
        assert!(ahead.next_frame().unwrap().is_some());
    }
    assert_eq!(ahead.next_frame().unwrap_err().to_string(), err.to_string());
    assert!(ahead.next_frame().unwrap().is_none());
}

#[test]
fn reading_ahead_gives_the_same_frames_errors_and_info() {
    let dir = tempfile::tempdir().unwrap();
    let h264 = encode(dir.path(), "clip.mp4", 12, H264_WITH_MOTION);
    let direct = drain(open(&h264).unwrap().as_mut()).unwrap();
    for ahead in [0, 1, 3, 50] {
        let mut src = open_ahead(&h264, true, ahead).unwrap();
        assert_eq!(src.info(), open(&h264).unwrap().info());
        let frames = drain(&mut src).unwrap();
        assert_eq!(frames.len(), direct.len());
        for (a, b) in frames.iter().zip(&direct) {
            assert_eq!((a.index, &a.rgb), (b.index, &b.rgb));
            assert_eq!(
                a.motion.as_ref().map(|m| &m.data),
                b.motion.as_ref().map(|m| &m.data)
            );
        }
        // After the end, the end again.
        assert!(src.next_frame().unwrap().is_none());
    }
    // Dropped part-way, with frames waiting to be handed on: no hang.
    let mut src = open_ahead(&h264, false, 2).unwrap();
    assert!(src.next_frame().unwrap().is_some());
    drop(src);
    // Opening errors come back from the opening call; decoding errors in their place.
    assert!(matches!(
        open_ahead(&dir.path().join("missing.mp4"), true, 2),
        Err(MediaError::Unreadable { .. })
    ));
    let frames = dir.path().join("frames");
    std::fs::create_dir(&frames).unwrap();
    let err = open_ahead(&frames, true, 2).err().expect("an empty folder");
    assert_eq!(err.to_string(), open(&frames).err().unwrap().to_string());
}
