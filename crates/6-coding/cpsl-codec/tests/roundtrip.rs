//! Coding layered frames into a package and reading them back, on the synthetic scene with
//! moving objects.

use cpsl_codec::{
    decode_segment, decode_stream, encode_stream, has_encoder, CodingOptions, PackageWriter,
    RateControl, SegmentReader,
};
use cpsl_core::{Edc, Layer, LayerSet, LayeredFrame, Limits, Pose, PremulImage, RefreshReason};
use cpsl_layering::LayeringConfig;
use cpsl_package::{Codec, Package};
use cpsl_synth::Scene;
use cpsl_temporal::{GopConfig, VideoLayerer};
use std::path::Path;

const W: u32 = 320;
const H: u32 = 240;
const FPS: f64 = 10.0;
const GOP: u32 = 6;

/// Layered frames of the synthetic clip, grouped into segments (GOP 6).
fn segments(frames: usize) -> Vec<Vec<LayeredFrame>> {
    segments_at(W, H, frames)
}

/// [`segments`] at `w x h`.
fn segments_at(w: u32, h: u32, frames: usize) -> Vec<Vec<LayeredFrame>> {
    let scene = Scene::default_scene(w, h);
    let gop = GopConfig {
        gop: GOP as usize,
        ..GopConfig::default()
    };
    let mut lay = VideoLayerer::new(scene.camera, LayeringConfig::default(), gop).unwrap();
    let mut out: Vec<Vec<LayeredFrame>> = Vec::new();
    for t in 0..frames {
        let v = scene.render(&scene.camera, &Pose::IDENTITY, t as f64 / FPS, 2);
        let f = lay.push(&v.rgb, Some(&v.depth)).unwrap();
        assert_eq!(f.index, t as u32);
        if f.refresh.is_some() {
            out.push(Vec::new());
        }
        out.last_mut().unwrap().push(f);
    }
    out
}

fn psnr(a: &LayerSet, b: &LayerSet) -> f64 {
    let (x, y) = (a.composite_reference(), b.composite_reference());
    let mse: f64 = x
        .iter()
        .zip(&y)
        .flat_map(|(p, q)| (0..3).map(move |c| ((p[c] - q[c]) as f64 * 255.0).powi(2)))
        .sum::<f64>()
        / (x.len() * 3) as f64;
    10.0 * (255.0f64 * 255.0 / mse.max(1e-12)).log10()
}

/// H.264 at `rate`, GOP 6, the default container.
fn h264(rate: RateControl) -> CodingOptions {
    CodingOptions {
        codec: Codec::H264,
        rate,
        fps: FPS,
        gop: GOP,
        container: cpsl_codec::Container::Fragment,
        segments: cpsl_codec::Segments::default(),
    }
}

fn write(
    out: &Path,
    segs: &[Vec<LayeredFrame>],
    opts: CodingOptions,
) -> Vec<cpsl_codec::SegmentReport> {
    let cam = *segs[0][0].set.camera();
    let mut w = PackageWriter::create(out, cam, 6, opts).unwrap();
    // Frame by frame: each I-frame closes the segment before it.
    let mut reports: Vec<_> = segs
        .iter()
        .flatten()
        .filter_map(|f| w.push(f.clone()).unwrap())
        .collect();
    reports.extend(w.flush().unwrap());
    assert_eq!(
        reports.len(),
        segs.len(),
        "one segment per group of pictures"
    );
    assert!(w.flush().unwrap().is_none(), "nothing left to code");
    w.finish().unwrap();
    reports
}

#[test]
fn package_round_trip_meets_budget_and_quality() {
    let segs = segments(12);
    assert!(
        segs.len() >= 2,
        "GOP 6 over 12 frames gives at least two segments"
    );
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("clip.cpsl");
    let budget = 800_000.0;
    let opts = h264(RateControl::Budget(budget));
    let reports = write(&out, &segs, opts);
    eprintln!("{reports:?}");
    let pkg = Package::open(&out).unwrap();
    assert!(pkg.verify().is_empty(), "{:?}", pkg.verify());
    let m = pkg.manifest();
    assert_eq!(m.frames, 12);
    for r in &reports {
        let b = r.budget_bits.unwrap();
        assert!(r.bits <= 1.1 * b, "segment spent {} bits of {b}", r.bits);
        // Generous for this size: full size (two trials per stream, a third at the best
        // quality where the budget reaches it, and the final encode), chosen without fitting
        // the half-size rung (its 18 trial encodes would bring the count to 42).
        assert!(r.scale.iter().all(|&s| s == 1) && r.encodes <= 24, "{r:?}");
    }
    // The first segment fits every stream by trial encodes; the next starts from the models
    // it carried on, and codes each stream once.
    assert_eq!(reports[0].fitted, reports[0].quality.len());
    assert!(
        reports[1].fitted < reports[1].quality.len(),
        "{:?}",
        reports[1]
    );
    assert!(reports[1].encodes < reports[0].encodes);
    let rate = m.bitrate();
    assert!(
        rate <= 1.1 * budget,
        "{rate} bit/s for a budget of {budget}"
    );
    assert!(
        rate >= 0.5 * budget,
        "{rate} bit/s leaves most of {budget} unused"
    );
    let e = SegmentReader::open(&pkg, segs.len())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains(&format!("no segment {}", segs.len())), "{e}");
    // Salient / edge-rich layers get more weight and no worse quality than the background.
    let mut worst = f64::INFINITY;
    for (i, seg) in segs.iter().enumerate() {
        let dec = decode_segment(&pkg, i).unwrap();
        assert_eq!(dec.len(), seg.len());
        // Frame by frame, as a player reads: the same pictures, then the end for good.
        let mut reader = SegmentReader::open(&pkg, i).unwrap();
        assert_eq!(reader.frames() as usize, seg.len());
        for d in &dec {
            let r = reader.next().unwrap().unwrap();
            for (a, b) in r.set.layers().iter().zip(d.set.layers()) {
                assert_eq!(a.image.as_bytes(), b.image.as_bytes());
            }
        }
        assert!(reader.next().is_none() && reader.next().is_none());
        for (d, s) in dec.iter().zip(seg) {
            assert_eq!(d.set.len(), s.set.len());
            assert_eq!(d.side.edc, cpsl_package::summarise_edc(&s.edc));
            for (a, b) in d.set.layers().iter().zip(s.set.layers()) {
                assert!((a.depth - b.depth).abs() <= 1e-5 * b.depth);
            }
            worst = worst.min(psnr(&d.set, &s.set));
        }
    }
    eprintln!("worst decoded reference-view PSNR at {budget} bit/s: {worst:.2} dB");
    // The side stream's per-pair EDC summary renders the Dynamic Pixel Strip as the full cache.
    let pose = cpsl_core::Pose::from_euler_deg(cpsl_core::Vec3::new(0.4, 0.1, 0.5), 3.0, -8.0, 0.0);
    let mut strips = 0;
    for f in segs.iter().flatten() {
        let render = |edc: &cpsl_core::Edc| {
            let p = cpsl_render::PreparedLayers::new(&f.set).with_edc(edc);
            let mut img = cpsl_core::PremulImage::new(f.set.camera().width, f.set.camera().height);
            let stats = p.render_dps_into(&pose, f.set.camera(), &mut img, &Default::default());
            (img, stats.pixels)
        };
        let ((full, n), (summary, m)) =
            (render(&f.edc), render(&cpsl_package::summarise_edc(&f.edc)));
        let close = full
            .as_bytes()
            .iter()
            .zip(summary.as_bytes())
            .all(|(a, b)| a.abs_diff(*b) <= 2);
        assert!(
            close && n.abs_diff(m) <= n / 50 + 2,
            "frame {}: {n} vs {m} strip pixels",
            f.index
        );
        strips += n;
    }
    assert!(strips > 0, "the clip exercises the strip");
    assert!(worst >= 30.0, "decoded layers at {worst:.2} dB");

    // Replacing the package works; a folder that is not a package is never replaced.
    let other = dir.path().join("other");
    std::fs::create_dir(&other).unwrap();
    let cam = *segs[0][0].set.camera();
    assert!(PackageWriter::create(&other, cam, 6, opts).is_err());
}

#[test]
fn a_budget_below_the_full_size_floor_codes_smaller_streams() {
    // Large enough for the pictures, not the MP4 headers, to set the floor.
    let segs = segments_at(640, 480, 6);
    let dir = tempfile::tempdir().unwrap();
    // The floor: every stream at full size and the lowest quality.
    let floor_pkg = dir.path().join("floor.cpsl");
    write(&floor_pkg, &segs, h264(RateControl::Quality(51.0)));
    let floor = Package::open(&floor_pkg).unwrap().manifest().bitrate();
    let budget = 0.7 * floor;
    let out = dir.path().join("small.cpsl");
    let reports = write(&out, &segs, h264(RateControl::Budget(budget)));
    eprintln!("floor {floor:.0} bit/s, budget {budget:.0}: {reports:?}");
    let pkg = Package::open(&out).unwrap();
    assert!(pkg.verify().is_empty());
    let m = pkg.manifest();
    assert!(m.bitrate() <= 1.1 * budget, "{} of {budget}", m.bitrate());
    assert!(reports.iter().all(|r| r.feasible));
    let scales: Vec<u32> = m
        .segments
        .iter()
        .flat_map(|s| s.streams.iter().map(|t| t.scale))
        .collect();
    assert!(scales.contains(&2), "{scales:?}");
    // Decoded at the frame size. On this saturated noise texture a half or quarter of the
    // resolution costs 3 to 4.5 dB against the full-size floor (which the budget cannot pay
    // for); the alignment of the upsampling is tested in `scale`.
    let floor_pkg = Package::open(&floor_pkg).unwrap();
    for (i, seg) in segs.iter().enumerate() {
        let (small, full) = (
            decode_segment(&pkg, i).unwrap(),
            decode_segment(&floor_pkg, i).unwrap(),
        );
        for ((d, f), s) in small.iter().zip(&full).zip(seg) {
            assert_eq!(d.set.camera(), s.set.camera());
            let (p, q) = (psnr(&d.set, &s.set), psnr(&f.set, &s.set));
            eprintln!(
                "frame {}: {p:.2} dB at {budget:.0} bit/s, {q:.2} dB at the floor",
                s.index
            );
            assert!(
                p >= q - 5.0,
                "frame {}: {p:.2} dB, {q:.2} at the floor",
                s.index
            );
        }
    }
}

#[test]
fn verify_detects_a_flipped_byte_in_every_part() {
    let segs = segments(4);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("clip.cpsl");
    let opts = h264(RateControl::Quality(30.0));
    write(&out, &segs, opts);
    let mut files = vec![out.join("manifest.json")];
    for f in Package::open(&out).unwrap().manifest().files() {
        files.push(out.join(&f.path));
    }
    for f in &files {
        let orig = std::fs::read(f).unwrap();
        for at in [0, orig.len() / 3, orig.len() / 2, orig.len() - 1] {
            let mut bad = orig.clone();
            bad[at] ^= 0x20;
            std::fs::write(f, &bad).unwrap();
            let detected = match Package::open(&out) {
                Err(_) => true,
                Ok(p) => !p.verify().is_empty(),
            };
            assert!(
                detected,
                "a flipped byte at {at} of {} went unnoticed",
                f.display()
            );
        }
        std::fs::write(f, &orig).unwrap();
    }
    assert!(Package::open(&out).unwrap().verify().is_empty());
    // A truncated stream and a missing side stream are clear errors, not panics.
    let pkg = Package::open(&out).unwrap();
    let fragment = pkg.manifest().segments[0].fragment.as_ref();
    let stream = pkg.path_of(fragment.expect("version 6 segments share a fragment"));
    let bytes = std::fs::read(&stream).unwrap();
    std::fs::write(&stream, &bytes[..bytes.len() / 2]).unwrap();
    let e = decode_segment(&pkg, 0).unwrap_err().to_string();
    assert!(e.contains("layers.m4s"), "{e}");
    std::fs::remove_file(pkg.path_of(&pkg.manifest().segments[0].side)).unwrap();
    assert!(decode_segment(&pkg, 0).is_err());
    // Decoding a truncated stream directly fails or returns fewer pictures, without panic.
    let _ = decode_stream(&stream, W, H);
}

#[test]
fn every_codec_round_trips_a_layer_stream() {
    let segs = segments(3);
    let dir = tempfile::tempdir().unwrap();
    for codec in Codec::ALL {
        if !has_encoder(codec) {
            eprintln!(
                "skipping {}: this FFmpeg has no encoder for it",
                codec.name()
            );
            continue;
        }
        let layers: Vec<_> = segs[0].iter().map(|f| &f.set.layers()[0].image).collect();
        let path = dir.path().join(format!("{}.mp4", codec.name()));
        let q = cpsl_codec::quality_range(codec).2;
        let bytes = encode_stream(&path, &layers, codec, q, FPS).unwrap();
        assert!(bytes > 0);
        // No encoder banner (x264's user-data SEI, x265's info SEI) in the stream, and no
        // muxer banner in the file.
        let file = std::fs::read(&path).unwrap();
        for banner in [&b"x264 - core"[..], b"x265 (build", b"Lavf"] {
            assert!(
                !file.windows(banner.len()).any(|w| w == banner),
                "{}: {:?} in the stream",
                codec.name(),
                String::from_utf8_lossy(banner)
            );
        }
        let back = decode_stream(&path, W, H).unwrap();
        assert_eq!(back.len(), layers.len(), "{}", codec.name());
        for (a, b) in layers.iter().zip(&back) {
            let mse: f64 = a
                .as_bytes()
                .iter()
                .zip(b.as_bytes())
                .map(|(x, y)| (*x as f64 - *y as f64).powi(2))
                .sum::<f64>()
                / a.as_bytes().len() as f64;
            let p = 10.0 * (255.0f64.powi(2) / mse.max(1e-12)).log10();
            assert!(p >= 30.0, "{}: {p:.2} dB", codec.name());
        }
    }
}

#[test]
fn a_package_archive_reads_like_its_folder() {
    let segs = segments(4);
    let dir = tempfile::tempdir().unwrap();
    let folder = dir.path().join("clip.cpsl");
    let opts = h264(RateControl::Quality(30.0));
    write(&folder, &segs, opts);
    let archive = dir.path().join("clip.tar.cpsl");
    let size = cpsl_package::pack(&folder, &archive).unwrap();
    assert!(cpsl_package::is_archive(&archive) && cpsl_package::is_package(&archive));
    assert!(!cpsl_package::is_archive(&folder));
    // Deterministic: packing again gives the same bytes.
    let again = dir.path().join("again.cpsl");
    cpsl_package::pack(&folder, &again).unwrap();
    assert_eq!(
        std::fs::read(&archive).unwrap(),
        std::fs::read(&again).unwrap()
    );
    assert_eq!(std::fs::metadata(&archive).unwrap().len(), size);
    let (a, b) = (
        Package::open(&folder).unwrap(),
        Package::open(&archive).unwrap(),
    );
    assert_eq!(a.manifest(), b.manifest());
    assert!(b.verify().is_empty());
    let (fa, fb) = (
        decode_segment(&a, 0).unwrap(),
        decode_segment(&b, 0).unwrap(),
    );
    assert_eq!(fa.len(), fb.len());
    for (x, y) in fa.iter().zip(&fb) {
        assert_eq!(x.set, y.set);
    }
    // The unpacked copy goes away with the package.
    let unpacked = b.root().to_path_buf();
    drop(b);
    assert!(!unpacked.exists());
    // A flipped byte inside a stream is caught by the checksums, as in a folder.
    let mut bytes = std::fs::read(&archive).unwrap();
    let at = bytes.len() / 2;
    bytes[at] ^= 0x20;
    std::fs::write(&again, &bytes).unwrap();
    // Messages name the archive (and the member), never the folder it was unpacked into.
    let messages: Vec<String> = match Package::open(&again) {
        Err(e) => vec![e.to_string()],
        Ok(p) => p.verify().iter().map(|e| e.to_string()).collect(),
    };
    assert!(!messages.is_empty());
    for m in &messages {
        assert!(
            m.contains(&again.display().to_string()) && !m.contains("cpsl-package-"),
            "{m}"
        );
    }
    // Packing refuses to replace something that is not an archive, and a damaged package.
    assert!(cpsl_package::pack(&folder, &folder.join("manifest.json")).is_err());
    let side = folder.join(&a.manifest().segments[0].side.path);
    std::fs::write(&side, b"damaged").unwrap();
    assert!(cpsl_package::pack(&folder, &dir.path().join("new.cpsl")).is_err());
    assert!(!dir.path().join("new.cpsl").exists());
}

#[test]
fn every_codec_carries_ten_bit_pictures() {
    use cpsl_codec::yuv::{stack_colour_grey16, unstack_colour_grey16, Yuv420};
    use cpsl_codec::{decode_pictures, encode_pictures};
    let (w, h) = (64u32, 64u32);
    let rgb: Vec<u8> = (0..w * h)
        .flat_map(|i| [(i % 251) as u8, 90, 160])
        .collect();
    // A smooth ramp down the picture over the whole 16-bit range: more levels than 8 bits
    // can hold.
    let grey: Vec<u16> = (0..w * h)
        .map(|i| (i as u64 * 65535 / (w * h - 1) as u64) as u16)
        .collect();
    let dir = tempfile::tempdir().unwrap();
    for codec in Codec::ALL {
        if !has_encoder(codec) {
            eprintln!("skipping {}: no encoder in this FFmpeg", codec.name());
            continue;
        }
        let path = dir.path().join(format!("{}.mp4", codec.name()));
        let q = cpsl_codec::quality_range(codec).0;
        let pic = |_| stack_colour_grey16(&rgb, &grey, w, h);
        encode_pictures(&path, 3, &pic, codec, q, FPS).unwrap();
        let back: Vec<Yuv420<u16>> = decode_pictures(&path, w, h).unwrap();
        assert_eq!(back.len(), 3, "{}", codec.name());
        let (_, g) = unstack_colour_grey16(&back[2], w, h);
        let err = g
            .iter()
            .zip(&grey)
            .map(|(a, b)| (*a as f64 - *b as f64).abs())
            .sum::<f64>()
            / grey.len() as f64;
        let mut levels = g.clone();
        levels.sort_unstable();
        levels.dedup();
        eprintln!(
            "{}: mean error {err:.1} of 65535, {} levels",
            codec.name(),
            levels.len()
        );
        // One 10-bit level is 75 of 65535; 8 bits would leave at most 220 levels.
        assert!(err < 75.0, "{}: mean error {err:.1}", codec.name());
        assert!(
            levels.len() > 220,
            "{}: {} levels",
            codec.name(),
            levels.len()
        );
        // Read as 8-bit, the stream is refused with its format named.
        let e = decode_pictures::<u8>(&path, w, h).unwrap_err().to_string();
        assert!(e.contains("YUV420P10LE"), "{e}");
    }
}

#[test]
fn frames_out_of_order_are_refused() {
    let segs = segments(3);
    let frames: Vec<LayeredFrame> = segs.into_iter().flatten().collect();
    let dir = tempfile::tempdir().unwrap();
    let opts = h264(RateControl::Quality(30.0));
    let out = dir.path().join("clip.cpsl");
    let mut w = PackageWriter::create(&out, *frames[0].set.camera(), 6, opts).unwrap();
    w.push(frames[0].clone()).unwrap();
    let e = w.push(frames[2].clone()).unwrap_err().to_string();
    assert!(e.contains("frame 1 expected"), "{e}");
    // The refused frame changed nothing: the right one is taken.
    w.push(frames[1].clone()).unwrap();
    w.push(frames[2].clone()).unwrap();
    assert_eq!(w.finish().unwrap().frames, 3);
}

#[test]
fn a_segments_fragment_after_an_init_segment_plays_its_layers_one_after_another() {
    // Version 6: one file per segment, one track run per layer stream. An ordinary MP4
    // demuxer (FFmpeg's) reads init + fragment as one track: the streams' pictures in turn.
    let segs = segments(GOP as usize);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("clip.cpsl");
    let opts = h264(RateControl::Quality(30.0));
    write(&out, &segs, opts);
    let pkg = Package::open(&out).unwrap();
    let m = pkg.manifest();
    assert_eq!(m.version, cpsl_package::SEGMENT_FRAGMENT_VERSION);
    let seg = &m.segments[0];
    assert!(seg.streams.len() >= 2 && seg.streams.iter().all(|t| t.file.is_none()));
    let fragment = std::fs::read(pkg.path_of(seg.fragment.as_ref().unwrap())).unwrap();
    let init = m.init_of(&seg.streams[0]).unwrap();
    let mut bytes = std::fs::read(pkg.path_of(init)).unwrap();
    bytes.extend(&fragment);
    let joined = dir.path().join("joined.mp4");
    std::fs::write(&joined, bytes).unwrap();
    let standard = cpsl_codec::decode_pictures::<u8>(&joined, W, H).unwrap();
    let n = seg.frames as usize;
    assert_eq!(standard.len(), n * seg.streams.len());
    // Each run decodes on its own to the same pictures.
    let shared: std::sync::Arc<[u8]> = fragment.into();
    for k in 0..seg.streams.len() {
        let mut r = cpsl_codec::PictureReader::<u8>::open_run(
            &joined,
            shared.clone(),
            k,
            Codec::H264,
            W,
            H,
        )
        .unwrap();
        let alone: Vec<_> = std::iter::from_fn(|| r.next_picture().unwrap()).collect();
        assert_eq!(alone.len(), n);
        assert!(alone[..] == standard[k * n..(k + 1) * n], "stream {k}");
    }
    // A fragment per stream (versions 4 and 5, for older players): the same pictures.
    let older = dir.path().join("older.cpsl");
    let opts = CodingOptions {
        container: cpsl_codec::Container::StreamFragments,
        segments: cpsl_codec::Segments::default(),
        ..opts
    };
    write(&older, &segs, opts);
    let old = Package::open(&older).unwrap();
    assert_eq!(old.manifest().version, cpsl_package::FRAGMENT_VERSION);
    let old_seg = &old.manifest().segments[0];
    assert!(old_seg.fragment.is_none() && old_seg.streams.iter().all(|t| t.file.is_some()));
    let (a, b) = (
        decode_segment(&pkg, 0).unwrap(),
        decode_segment(&old, 0).unwrap(),
    );
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert!(psnr(&x.set, &y.set) > 99.0);
    }
    // The shared fragment saves each stream but one the fragment's boxes (56 bytes).
    let bytes = |p: &Package| p.manifest().payload_bytes();
    assert_eq!(
        bytes(&old) - bytes(&pkg),
        56 * (seg.streams.len() as u64 - 1)
    );
}

/// A 64x48 frame of two layers with tracks `tracks`: a near square whose left edge is at
/// `x0`, and the background.
fn two_layers(
    index: u32,
    refresh: Option<RefreshReason>,
    tracks: [u32; 2],
    x0: usize,
) -> LayeredFrame {
    let cam = cpsl_core::Camera::from_fov(64, 48, 60.0);
    let mut near = PremulImage::new(64, 48);
    let mut far = PremulImage::new(64, 48);
    for y in 0..48 {
        for x in 0..64 {
            far.as_bytes_mut()[(y * 64 + x) * 4..][..4].copy_from_slice(&[
                40,
                90,
                (4 * x) as u8,
                255,
            ]);
            if (x0..x0 + 24).contains(&x) && (12..36).contains(&y) {
                near.as_bytes_mut()[(y * 64 + x) * 4..][..4].copy_from_slice(&[
                    200,
                    (5 * y) as u8,
                    30,
                    255,
                ]);
            }
        }
    }
    let layers = [(near, 2.0, tracks[0]), (far, 5.0, tracks[1])]
        .into_iter()
        .map(|(image, z, t)| {
            let mut l = Layer::new(image, z);
            l.meta.track = Some(t);
            l
        })
        .collect();
    let set = LayerSet::new_premultiplied(cam, layers, &Limits::default()).unwrap();
    LayeredFrame::new(index, refresh, set, Edc::empty(64, 48, 2, 1.0 / 64.0))
}

/// Writes `frames` as a package at `out` with `opts` (two layers), frame by frame, the writer
/// told how many are left when the length is `known`.
fn write_frames(
    out: &Path,
    frames: &[LayeredFrame],
    opts: CodingOptions,
    known: bool,
) -> cpsl_package::PackageManifest {
    let mut w = PackageWriter::create(out, *frames[0].set.camera(), 2, opts).unwrap();
    for (i, f) in frames.iter().enumerate() {
        w.set_frames_left(known.then_some((frames.len() - i) as u32));
        w.push(f.clone()).unwrap();
    }
    w.finish().unwrap()
}

#[test]
fn a_refresh_for_changed_content_moves_the_models_by_one_trial_each() {
    // The second segment starts at a refresh for lost confidence that keeps the tracks: its
    // streams start from the first segment's models, each moved onto the new content by one
    // trial encode instead of being fitted again.
    let mut segs = segments(12);
    segs[1][0].refresh = Some(RefreshReason::Confidence);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("clip.cpsl");
    let budget = 800_000.0;
    let reports = write(&out, &segs, h264(RateControl::Budget(budget)));
    let streams = reports[1].quality.len();
    assert_eq!(reports[0].fitted, streams);
    assert_eq!(reports[1].fitted, 0, "{:?}", reports[1]);
    // One trial and the final encode per stream.
    assert_eq!(reports[1].encodes, 2 * streams, "{:?}", reports[1]);
    for r in &reports {
        let b = r.budget_bits.unwrap();
        assert!(r.bits <= 1.1 * b, "segment spent {} bits of {b}", r.bits);
    }
    let pkg = Package::open(&out).unwrap();
    assert!(pkg.verify().is_empty(), "{:?}", pkg.verify());
    assert!(pkg.manifest().bitrate() >= 0.5 * budget);
}

#[test]
fn a_segment_that_may_be_the_last_moves_its_models_by_one_trial_each() {
    // Frames pushed without their number: every segment may be the last, whose miss would be
    // corrected by coding its streams again, so each carried model is first moved onto the
    // segment's content by one trial encode (as after a refresh for changed content).
    let segs = segments(18);
    assert_eq!(segs.len(), 3);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("clip.cpsl");
    let reports = write(&out, &segs, h264(RateControl::Budget(800_000.0)));
    let streams = reports[0].quality.len();
    assert_eq!(reports[0].fitted, streams);
    for r in &reports[1..] {
        // The carried models serve (a stream whose trial lands more than twice off its model
        // is fitted again).
        assert!(r.fitted < streams, "{r:?}");
        // One trial and the final encode per stream, and any refit's or correction's encodes.
        assert!(r.encodes >= 2 * streams, "{r:?}");
    }
    // Told how many frames are left, only the last segment may be the last: the middle one
    // codes each stream once.
    let frames: Vec<LayeredFrame> = segs.into_iter().flatten().collect();
    let cam = *frames[0].set.camera();
    let out = dir.path().join("known.cpsl");
    let mut w = PackageWriter::create(&out, cam, 6, h264(RateControl::Budget(800_000.0))).unwrap();
    let mut reports = Vec::new();
    for (i, f) in frames.iter().enumerate() {
        w.set_frames_left(Some((frames.len() - i) as u32));
        reports.extend(w.push(f.clone()).unwrap());
    }
    reports.extend(w.flush().unwrap());
    w.finish().unwrap();
    assert_eq!(reports.len(), 3);
    assert_eq!(reports[1].encodes, streams, "{:?}", reports[1]);
    assert!(reports[2].encodes >= 2 * streams, "{:?}", reports[2]);
}

#[test]
fn segments_start_every_gop_and_at_refreshes_that_bring_new_layers() {
    use RefreshReason::{Confidence, First};
    // GOP 4 over 9 frames: a refresh at frame 2 keeps both tracks, one at frame 6 brings a
    // new background layer (track 7).
    let frames: Vec<LayeredFrame> = (0..9u32)
        .map(|i| {
            let (refresh, tracks) = match i {
                0 => (Some(First), [0, 1]),
                2 => (Some(Confidence), [0, 1]),
                6 => (Some(Confidence), [0, 7]),
                7.. => (None, [0, 7]),
                _ => (None, [0, 1]),
            };
            two_layers(i, refresh, tracks, 4 + 3 * i as usize)
        })
        .collect();
    let starts = |segments: cpsl_codec::Segments, known: bool| {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("clip.cpsl");
        let opts = CodingOptions {
            gop: 4,
            segments,
            ..h264(RateControl::Quality(18.0))
        };
        write_frames(&out, &frames, opts, known);
        let pkg = Package::open(&out).unwrap();
        assert!(pkg.verify().is_empty(), "{:?}", pkg.verify());
        // Every frame decodes to its own layers, through the refreshes inside segments too.
        let decoded: Vec<_> = (0..pkg.manifest().segments.len())
            .flat_map(|s| decode_segment(&pkg, s).unwrap())
            .collect();
        assert_eq!(decoded.len(), frames.len());
        for (d, f) in decoded.iter().zip(&frames) {
            assert!(psnr(&d.set, &f.set) > 30.0, "frame {}", f.index);
            let tracks: Vec<_> = d.set.layers().iter().map(|l| l.meta.track).collect();
            let want: Vec<_> = f.set.layers().iter().map(|l| l.meta.track).collect();
            assert_eq!(tracks, want, "frame {}", f.index);
        }
        let starts: Vec<u32> = pkg.manifest().segments.iter().map(|s| s.start).collect();
        starts
    };
    // By the clock: frame 2's refresh continues the streams, frame 6's new layer cuts.
    assert_eq!(starts(cpsl_codec::Segments::Gop, false), [0, 4, 6]);
    assert_eq!(starts(cpsl_codec::Segments::Gop, true), [0, 4, 6]);
    // At every refresh, as the paper's groups of pictures (frame 4 continues frame 2's).
    assert_eq!(starts(cpsl_codec::Segments::Refresh, true), [0, 2, 6]);
}

#[test]
fn under_a_budget_segments_decode_whether_or_not_the_frames_left_are_known() {
    // With the frames left known, only the last segment keeps its pictures on disk for a
    // correction round and the others are coded as the frames arrive; unknown, every segment
    // keeps them. Either way every frame decodes, the package keeps to its budget and no
    // spill file is left behind.
    let frames: Vec<LayeredFrame> = (0..12u32)
        .map(|i| {
            let refresh = (i == 0).then_some(RefreshReason::First);
            two_layers(i, refresh, [0, 1], 4 + 3 * i as usize)
        })
        .collect();
    let budget = 20_000.0;
    let coded = |known: bool| {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("clip.cpsl");
        let opts = CodingOptions {
            gop: 4,
            ..h264(RateControl::Budget(budget))
        };
        let manifest = write_frames(&out, &frames, opts, known);
        let pkg = Package::open(&out).unwrap();
        assert!(pkg.verify().is_empty(), "{:?}", pkg.verify());
        let decoded: Vec<_> = (0..manifest.segments.len())
            .flat_map(|s| decode_segment(&pkg, s).unwrap())
            .collect();
        assert_eq!(decoded.len(), frames.len());
        for (d, f) in decoded.iter().zip(&frames) {
            assert!(psnr(&d.set, &f.set) > 30.0, "frame {}", f.index);
        }
        let rate = manifest.bitrate();
        assert!(rate <= 1.1 * budget && rate >= 0.5 * budget, "{rate} bit/s");
        // No spilled pictures are left behind.
        let left: Vec<_> = walk(&out)
            .into_iter()
            .filter(|p| p.to_string_lossy().ends_with(".part"))
            .collect();
        assert!(left.is_empty(), "{left:?}");
        manifest.segments.len()
    };
    assert_eq!(coded(true), 3);
    assert_eq!(coded(false), 3);
}

fn walk(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        match p.is_dir() {
            true => out.extend(walk(&p)),
            false => out.push(p),
        }
    }
    out
}

#[test]
fn a_short_tail_joins_the_last_segment() {
    let frames: Vec<LayeredFrame> = (0..9u32)
        .map(|i| {
            two_layers(
                i,
                (i == 0).then_some(RefreshReason::First),
                [0, 1],
                4 + 3 * i as usize,
            )
        })
        .collect();
    let starts = |known: bool| {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("clip.cpsl");
        let opts = CodingOptions {
            gop: 4,
            ..h264(RateControl::Quality(30.0))
        };
        write_frames(&out, &frames, opts, known)
            .segments
            .iter()
            .map(|s| (s.start, s.frames))
            .collect::<Vec<_>>()
    };
    // GOP 4 over 9 frames: a one-frame segment at the end unless the writer knows it comes.
    assert_eq!(starts(false), [(0, 4), (4, 4), (8, 1)]);
    assert_eq!(starts(true), [(0, 4), (4, 5)]);
}
