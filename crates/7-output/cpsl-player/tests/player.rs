//! The player seeks anywhere in a package (forwards within a segment, backwards, into other
//! segments) and always hands out the frame asked for; sources open packages and layer sets.

use cpsl_codec::{CodingOptions, PackageWriter, RateControl};
use cpsl_core::{Edc, LayerSet, LayeredFrame, RefreshReason};
use cpsl_package::Codec;
use cpsl_player::{Player, PlayerError, Source};
use cpsl_synth::layers::{synthetic_layer_set, Coverage};

const FRAMES: u32 = 7;

/// Frame `i`'s layers: noise textures seeded by `i`, so every frame looks different.
fn set(i: u32) -> LayerSet {
    synthetic_layer_set(64, 48, 2, Coverage::Typical, 100 + i as u64)
}

/// Mean absolute difference of two sets' layer bytes.
fn diff(a: &LayerSet, b: &LayerSet) -> f64 {
    let (mut sum, mut n) = (0u64, 0usize);
    for (x, y) in a.layers().iter().zip(b.layers()) {
        for (p, q) in x.image.as_bytes().iter().zip(y.image.as_bytes()) {
            sum += p.abs_diff(*q) as u64;
            n += 1;
        }
    }
    sum as f64 / n as f64
}

#[test]
fn seeks_anywhere_and_opens_every_source() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("clip.cpsl");
    let sets: Vec<LayerSet> = (0..FRAMES).map(set).collect();
    let opts = CodingOptions {
        codec: Codec::H264,
        rate: RateControl::Quality(12.0),
        fps: 10.0,
        gop: 4,
        container: cpsl_codec::Container::Fragment,
        segments: cpsl_codec::Segments::default(),
    };
    let mut writer = PackageWriter::create(&path, *sets[0].camera(), 2, opts).unwrap();
    for (i, s) in sets.iter().enumerate() {
        // Two segments: frames 0-3 and 4-6.
        let refresh = match i {
            0 => Some(RefreshReason::First),
            4 => Some(RefreshReason::Gop),
            _ => None,
        };
        let edc = Edc::empty(64, 48, 2, 1.0 / 128.0);
        writer
            .push(LayeredFrame::new(i as u32, refresh, s.clone(), edc))
            .unwrap();
    }
    assert_eq!(writer.finish().unwrap().segments.len(), 2);

    let mut player = Player::open(&path).unwrap();
    assert_eq!(player.frames(), FRAMES);
    // Forwards inside a segment, backwards, across segments and back to the start.
    for f in [5, 6, 2, 3, 0, 6, 1, 4] {
        let decoded = player.decode(f).unwrap();
        assert!(decoded.edc.is_some(), "frame {f} comes with its cache");
        let own = diff(&decoded.set, &sets[f as usize]);
        let other = diff(&decoded.set, &sets[((f + 1) % FRAMES) as usize]);
        assert!(
            own < 4.0 && own * 3.0 < other,
            "frame {f}: {own} vs {other}"
        );
    }
    assert!(matches!(
        player.decode(FRAMES),
        Err(PlayerError::NoFrame {
            frame: 7,
            frames: 7
        })
    ));
    // The frame asked for is kept until another is.
    let kept = player.frame(3).unwrap() as *const _;
    assert_eq!(player.frame(3).unwrap() as *const _, kept);

    let mut source = Source::open(&path).unwrap();
    assert_eq!(source.frames(), FRAMES);
    assert!(diff(&source.at(FRAMES as usize + 2).unwrap().set, &sets[2]) < 4.0);
    let layers = dir.path().join("layers");
    cpsl_io::write_layer_set(&layers, &sets[0], &[]).unwrap();
    let mut still = Source::open(&layers).unwrap();
    assert_eq!(still.frames(), 1);
    assert_eq!(diff(&still.at(5).unwrap().set, &sets[0]), 0.0);
    let file = dir.path().join("note.txt");
    std::fs::write(&file, "not layers").unwrap();
    let e = Source::open(&file).err().unwrap().to_string();
    assert!(e.contains("is a file, not a layer-set folder"), "{e}");
    let e = Player::open(&layers).err().unwrap().to_string();
    assert!(e.contains("opening the package"), "{e}");
}

#[test]
fn plays_a_layered_video_folder_frame_by_frame() {
    let dir = tempfile::tempdir().unwrap();
    let video = dir.path().join("video");
    let names = ["frame_000000", "frame_000001", "frame_000002"];
    for (i, name) in names.iter().enumerate() {
        cpsl_io::write_layer_set(&video.join(name), &set(i as u32), &[]).unwrap();
    }
    let frames: Vec<String> = names
        .iter()
        .map(|n| format!("{{\"dir\": \"{n}\"}}"))
        .collect();
    let index = format!(
        "{{\"format\": \"cpsl-video-layers\", \"version\": 1, \"fps\": 24, \"frames\": [{}]}}",
        frames.join(", ")
    );
    std::fs::write(video.join("video.json"), index).unwrap();
    let Source::Video(mut v) = Source::open(&video).unwrap() else {
        panic!("not opened as a layered video")
    };
    assert_eq!((cpsl_player::Frames::frames(&*v), v.fps()), (3, 24.0));
    // Any frame in any order, each the layer set written for it.
    for f in [2, 0, 1, 1] {
        assert_eq!(v.frame(f).unwrap().set, set(f));
    }
    assert!(matches!(
        v.frame(3),
        Err(PlayerError::NoFrame {
            frame: 3,
            frames: 3
        })
    ));
    // A frame with another camera is refused, naming its folder (frame 1 read again: the
    // frame asked for last is kept).
    v.frame(0).unwrap();
    let other = synthetic_layer_set(32, 24, 2, Coverage::Typical, 1);
    cpsl_io::write_layer_set(&video.join(names[1]), &other, &[]).unwrap();
    let e = v.frame(1).err().unwrap().to_string();
    assert!(e.contains("frame_000001") && e.contains("camera"), "{e}");
    // A broken index says which file and field.
    std::fs::write(
        video.join("video.json"),
        "{\"format\": \"cpsl-video-layers\", \"version\": 1, \"fps\": 24, \"frames\": []}",
    )
    .unwrap();
    let e = Source::open(&video).err().unwrap().to_string();
    assert!(e.contains("video.json") && e.contains("frames"), "{e}");
}
