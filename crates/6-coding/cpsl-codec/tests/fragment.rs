//! Fragmented layer streams: a fragment decodes on its own to the pictures a self-contained
//! MP4 file of the same encoder settings holds, and its init segment followed by it is an
//! ordinary fragmented MP4 that FFmpeg's demuxer reads.

use cpsl_codec::yuv::Yuv420;
use cpsl_codec::{has_encoder, write_init, Container, PictureReader, StreamEncoder};
use cpsl_package::Codec;
use std::path::Path;

const FPS: f64 = 30.0;
const W: usize = 256;
const H: usize = 96;

/// A moving gradient, `n` stacked pictures of a `W x H` layer.
fn pictures(n: usize) -> Vec<Yuv420> {
    gradient(W, 2 * H, n)
}

/// A moving gradient, `n` pictures of `w x h`.
fn gradient(w: usize, h: usize, n: usize) -> Vec<Yuv420> {
    (0..n)
        .map(|t| Yuv420 {
            width: w,
            height: h,
            y: (0..w * h)
                .map(|i| ((i % w) * 2 + (i / w) + 5 * t) as u8)
                .collect(),
            u: (0..w * h / 4).map(|i| (100 + (i % 7) + t) as u8).collect(),
            v: vec![128; w * h / 4],
        })
        .collect()
}

fn encode(path: &Path, container: Container, codec: Codec, pics: &[Yuv420]) -> cpsl_codec::Written {
    let q = cpsl_codec::quality_range(codec).2;
    let mut e =
        StreamEncoder::<u8>::create_as(path, container, (W, 2 * H), codec, q, FPS, pics.len())
            .unwrap();
    for p in pics {
        e.push(p).unwrap();
    }
    e.finish().unwrap()
}

fn read(mut r: PictureReader) -> Vec<Yuv420> {
    std::iter::from_fn(|| r.next_picture().unwrap()).collect()
}

#[test]
fn fragments_decode_alone_and_after_their_init_segment() {
    let dir = tempfile::tempdir().unwrap();
    let pics = pictures(12);
    for codec in Codec::ALL {
        if !has_encoder(codec) {
            eprintln!("skipping {}: no encoder in this FFmpeg", codec.name());
            continue;
        }
        let name = codec.name();
        let mp4 = dir.path().join(format!("{name}.mp4"));
        let frag = dir.path().join(format!("{name}.m4s"));
        let whole = encode(&mp4, Container::Mp4, codec, &pics);
        let part = encode(&frag, Container::Fragment, codec, &pics);
        // The same pictures coded: the fragment saves the MP4 file's header and index.
        let coded: u64 = part.packets.iter().sum();
        let overhead = part.bytes - coded;
        eprintln!(
            "{name}: MP4 file {} B, fragment {} B ({overhead} B beyond its {} pictures)",
            whole.bytes,
            part.bytes,
            part.packets.len()
        );
        assert!(overhead <= 80 + 8 * 12, "{name}: {overhead} B of boxes");
        assert!(part.bytes + 500 < whole.bytes, "{name}");
        let from_mp4 = read(PictureReader::open(&mp4, W as u32, H as u32).unwrap());
        let alone = read(
            PictureReader::open_as(&frag, Container::Fragment, codec, W as u32, H as u32).unwrap(),
        );
        assert_eq!(alone.len(), 12, "{name}");
        assert!(
            alone == from_mp4,
            "{name}: the fragment decodes to other pictures"
        );
        // A wrong layer size is refused on opening.
        let e = PictureReader::<u8>::open_as(&frag, Container::Fragment, codec, W as u32, 100)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("256x200"), "{e}");

        // Init segment + fragment: a standard fragmented MP4 for FFmpeg's demuxer.
        let init = dir.path().join(format!("init-{name}.mp4"));
        let init_bytes = write_init::<u8>(&init, codec, (W, 2 * H), FPS, &part.headers).unwrap();
        assert!(init_bytes < 1500, "{name}: init segment of {init_bytes} B");
        let joined = dir.path().join(format!("joined-{name}.mp4"));
        let mut bytes = std::fs::read(&init).unwrap();
        bytes.extend(std::fs::read(&frag).unwrap());
        std::fs::write(&joined, bytes).unwrap();
        let standard = read(PictureReader::open(&joined, W as u32, H as u32).unwrap());
        assert!(standard == alone, "{name}: FFmpeg reads other pictures");
    }
}

#[test]
fn damaged_fragments_are_errors() {
    if !has_encoder(Codec::H264) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let frag = dir.path().join("a.m4s");
    encode(&frag, Container::Fragment, Codec::H264, &pictures(4));
    let good = std::fs::read(&frag).unwrap();
    for cut in [0, 20, 90, good.len() - 10] {
        std::fs::write(&frag, &good[..cut]).unwrap();
        let r = PictureReader::<u8>::open_as(
            &frag,
            Container::Fragment,
            Codec::H264,
            W as u32,
            H as u32,
        );
        assert!(r.is_err(), "cut at {cut}");
    }
}

#[test]
fn the_same_small_pictures_code_to_the_same_stream_every_time() {
    // x264 reads memory it never wrote on small pictures (see `fresh_large_allocations`):
    // the encoders before must not change what the next one writes.
    if !has_encoder(Codec::H264) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (96, 64);
    let pics = gradient(w, h, 12);
    let streams: Vec<Vec<u8>> = (0..4)
        .map(|r| {
            let p = dir.path().join(format!("{r}.m4s"));
            let mut e = StreamEncoder::<u8>::create_as(
                &p,
                Container::Fragment,
                (w, h),
                Codec::H264,
                23.0,
                FPS,
                12,
            )
            .unwrap();
            for x in &pics {
                e.push(x).unwrap();
            }
            e.finish().unwrap();
            std::fs::read(&p).unwrap()
        })
        .collect();
    assert!(streams.iter().all(|s| s == &streams[0]));
}
