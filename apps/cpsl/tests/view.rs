//! `cpsl view` under Xvfb: the window shows a layer set, a package frame and a layered video's
//! frame at a given pose,
//! and a screenshot of the screen (ImageMagick `import`) matches the CPU render of the same
//! pose and frame. Skips, saying why, without Xvfb, `import` or a GPU adapter (lavapipe
//! counts), unless `CPSL_REQUIRE_GPU=1` (set by `.ci/run`, which installs all three).

mod common;

use common::{ok, s};
use std::io::{BufRead, BufReader, Read};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn required() -> bool {
    std::env::var("CPSL_REQUIRE_GPU").as_deref() == Ok("1")
}

fn skip(why: &str) {
    assert!(!required(), "CPSL_REQUIRE_GPU=1 but {why}");
    eprintln!("skipping the viewer test: {why}");
}

fn have(tool: &str) -> bool {
    Command::new("sh")
        .args(["-c", &format!("command -v {tool}")])
        .output()
        .is_ok_and(|o| o.status.success())
}

/// A virtual X display, closed on drop.
struct Xvfb {
    child: Child,
    display: String,
}

impl Xvfb {
    fn start() -> Self {
        let mut child = Command::new("Xvfb")
            .args([
                "-displayfd",
                "1",
                "-screen",
                "0",
                "640x480x24",
                "-nolisten",
                "tcp",
            ])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("Xvfb starts");
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        Xvfb {
            child,
            display: format!(":{}", line.trim()),
        }
    }
}

impl Drop for Xvfb {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Opens the viewer with `args`, waits for its first frame, screenshots the screen and returns
/// the top-left `w x h` pixels; `None` when there is no adapter (and none is required).
fn screenshot(x: &Xvfb, args: &[&str], w: u32, h: u32, dir: &Path) -> Option<Vec<u8>> {
    let mut viewer = Command::new(env!("CARGO_BIN_EXE_cpsl"))
        .arg("view")
        .args(args)
        .args(["--paused", "--no-hud", "--exit-after", "60"])
        .env("DISPLAY", &x.display)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut out = BufReader::new(viewer.stdout.take().unwrap());
    let mut line = String::new();
    let t = Instant::now();
    let shown = loop {
        line.clear();
        if out.read_line(&mut line).unwrap_or(0) == 0 {
            break false;
        }
        if line.starts_with("shown on") {
            break true;
        }
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "the viewer never drew"
        );
    };
    if !shown {
        let mut err = String::new();
        viewer
            .stderr
            .take()
            .unwrap()
            .read_to_string(&mut err)
            .unwrap();
        let _ = viewer.wait();
        if err.contains("no GPU adapter") {
            skip(err.trim());
            return None;
        }
        panic!("cpsl view {args:?} failed: {err}");
    }
    // A few more presented frames, then the screen as the X server holds it.
    std::thread::sleep(Duration::from_millis(700));
    let shot = dir.join("shot.png");
    let st = Command::new("import")
        .args(["-display", &x.display, "-window", "root", s(&shot)])
        .status()
        .unwrap();
    assert!(st.success(), "import failed");
    let _ = viewer.kill();
    let _ = viewer.wait();
    let img = cpsl_io::images::read_rgb8(&shot, &Default::default()).unwrap();
    let mut crop = Vec::with_capacity((w * h * 3) as usize);
    for y in 0..h as usize {
        let o = y * img.width as usize * 3;
        crop.extend_from_slice(&img.data[o..o + w as usize * 3]);
    }
    Some(crop)
}

#[test]
fn viewer_screenshot_matches_the_cpu_render() {
    for tool in ["Xvfb", "import"] {
        if !have(tool) {
            return skip(&format!(
                "{tool} is not installed (apt install xvfb imagemagick)"
            ));
        }
    }
    let d = tempfile::tempdir().unwrap();
    let scene = d.path().join("scene");
    let layers = d.path().join("layers");
    ok(&[
        "synth",
        "-o",
        s(&scene),
        "--width",
        "160",
        "--height",
        "120",
        "--supersample",
        "1",
    ]);
    ok(&[
        "slice",
        s(&scene.join("input.png")),
        "--depth",
        s(&scene.join("depth.pfm")),
        "--camera",
        s(&scene.join("camera.json")),
        "-o",
        s(&layers),
        "--layers",
        "4",
    ]);
    ok(&[
        "demo",
        "-o",
        s(&d.path().join("demo")),
        "--width",
        "128",
        "--height",
        "96",
        "--clip-frames",
        "12",
    ]);
    let package = d.path().join("demo/clip.cpsl");
    // The demo's clip layered into a folder of layer sets (`cpsl layer-video`), played as a
    // package is.
    let clip = d.path().join("demo/clip");
    let video = d.path().join("video");
    ok(&[
        "layer-video",
        s(&clip.join("frames")),
        "--camera",
        s(&clip.join("camera.json")),
        "--depth-frames",
        s(&clip.join("depth")),
        "-o",
        s(&video),
    ]);
    let x = Xvfb::start();
    // It looks past the frame's edge: the viewer fills what the layers leave uncovered as
    // the CPU render does (`--background fill`, the default).
    let pose = "0.05,0.01,0,1,2,0";
    let sources = [
        (&layers, "0", (160, 120)),
        (&package, "7", (128, 96)),
        (&video, "5", (128, 96)),
    ];
    for (source, frame, (w, h)) in sources {
        // The CPU's render of the same view with `filter`.
        let render = |filter: &str| {
            let out = d.path().join(format!("reference_{filter}.png"));
            ok(&[
                "render",
                s(source),
                "--frame",
                frame,
                "--pose",
                pose,
                "--filter",
                filter,
                "-o",
                s(&out),
            ]);
            cpsl_io::images::read_rgb8(&out, &Default::default()).unwrap()
        };
        let want = render("bilinear");
        let args = [s(source), "--frame", frame, "--pose", pose];
        let Some(got) = screenshot(&x, &args, w, h, d.path()) else {
            return;
        };
        let psnr = cpsl_eval::metrics::psnr(&got, &want.data);
        eprintln!(
            "{}: screenshot {psnr:.2} dB from the CPU render",
            source.display()
        );
        assert!(
            psnr >= 45.0,
            "{}: the viewer's screenshot is {psnr:.2} dB from the CPU render",
            source.display()
        );
        // Side-by-side stereo with the eyes together: both halves are that same view.
        let mut stereo = args.to_vec();
        stereo.extend(["--stereo", "--eye-separation", "0"]);
        let both = screenshot(&x, &stereo, 2 * w, h, d.path()).expect("adapter found before");
        for eye in 0..2usize {
            let half: Vec<u8> = both
                .chunks_exact(2 * w as usize * 3)
                .flat_map(|row| row[eye * w as usize * 3..(eye + 1) * w as usize * 3].to_vec())
                .collect();
            let psnr = cpsl_eval::metrics::psnr(&half, &want.data);
            assert!(psnr >= 45.0, "stereo eye {eye}: {psnr:.2} dB");
        }
        // The bicubic filter, against the CPU's bicubic render (the two filters' renders are
        // further apart than the check allows).
        let want_cubic = render("cubic");
        let apart = cpsl_eval::metrics::psnr(&want_cubic.data, &want.data);
        let mut sharp = args.to_vec();
        sharp.extend(["--filter", "cubic"]);
        let got = screenshot(&x, &sharp, w, h, d.path()).expect("adapter found before");
        let psnr = cpsl_eval::metrics::psnr(&got, &want_cubic.data);
        eprintln!(
            "{}: cubic screenshot {psnr:.2} dB from the CPU's (filters {apart:.2} dB apart)",
            source.display()
        );
        assert!(
            psnr >= 45.0 && apart < 45.0,
            "cubic: {psnr:.2} dB, filters {apart:.2} dB apart"
        );
    }
}
