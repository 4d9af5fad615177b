//! The GPU benchmark on a small frame: every geometry and coverage runs, is timed and matches
//! the CPU reference, and the binary needs no FFmpeg. Without an adapter the tests say so
//! and pass, unless `CPSL_REQUIRE_GPU=1` (set by `.ci/run`, which installs lavapipe).

use cpsl_core::Pose;
use cpsl_gpu_bench::{bench, GpuBench};
use cpsl_layering::GeometryMode;
use cpsl_render_gpu::{GpuRenderer, Passes};
use cpsl_synth::layers::Coverage;

fn gpu() -> Option<GpuRenderer> {
    match GpuRenderer::new() {
        Ok(g) => Some(g),
        Err(e) => {
            assert!(
                std::env::var("CPSL_REQUIRE_GPU").as_deref() != Ok("1"),
                "CPSL_REQUIRE_GPU=1 but {e}"
            );
            eprintln!("skipping: {e}");
            None
        }
    }
}

fn small() -> GpuBench {
    GpuBench {
        sizes: vec![(160, 96)],
        layers: vec![3],
        geometries: vec![
            GeometryMode::Plane,
            GeometryMode::Slanted,
            GeometryMode::Mesh,
        ],
        coverages: vec![Coverage::Typical, Coverage::Dense],
        passes: vec![Passes::Compute, Passes::Fragment],
        warm_up_s: 0.0,
        frames: 3,
        throughput_frames: 3,
        pose: Pose::parse("0.05,-0.02,0.03,0.4,-0.8,0.2").expect("pose"),
        min_psnr_db: 45.0,
    }
}

#[test]
fn every_case_is_timed_and_matches_the_cpu() {
    let Some(mut g) = gpu() else { return };
    let mut seen = 0;
    let report = bench(&mut g, &small(), |r| {
        seen += 1;
        assert_eq!(r.cases.len(), seen);
    })
    .expect("bench runs");
    // 3 geometries x 2 coverages x 2 ways to run the passes x with and without the strip.
    assert_eq!(report.cases.len(), 24);
    let passes: Vec<_> = report.cases.iter().map(|c| c.passes).collect();
    assert_eq!(&passes[..4], ["compute", "compute", "fragment", "fragment"]);
    for c in &report.cases {
        assert!(c.matches_cpu && c.psnr_vs_cpu_db >= 45.0, "{c:?}");
        assert!(c.fps > 0.0 && c.sustained_fps > 0.0, "{c:?}");
        assert_eq!(c.gpu.is_some(), report.adapter.timestamps, "{c:?}");
    }
    assert!(report.all_match);
    let json = serde_json::to_value(&report).expect("serialises");
    assert_eq!(json["cases"][23]["geometry"], "mesh");
    assert!(json["adapter"]["name"].is_string() && json["date"].is_string());
}

/// A GPU image that misses the bar is reported, not hidden.
#[test]
fn an_unreachable_bar_fails_the_cases() {
    let Some(mut g) = gpu() else { return };
    let mut a = small();
    a.geometries = vec![GeometryMode::Plane];
    a.coverages = vec![Coverage::Dense];
    a.passes = vec![Passes::Compute];
    a.min_psnr_db = 100.0;
    let report = bench(&mut g, &a, |_| {}).expect("bench runs");
    assert!(!report.all_match);
    assert!(report.cases.iter().all(|c| !c.matches_cpu));
}

/// The render benchmark must run where only a Vulkan driver is: no FFmpeg, no ONNX Runtime.
#[test]
fn the_render_binary_links_no_ffmpeg() {
    let bin = env!("CARGO_BIN_EXE_cpsl-gpu-bench");
    let Ok(out) = std::process::Command::new("ldd").arg(bin).output() else {
        eprintln!("skipping: no ldd");
        return;
    };
    let libs = String::from_utf8_lossy(&out.stdout);
    assert!(libs.contains("libc.so"), "{libs}");
    for lib in ["libav", "libsw", "onnxruntime", "opencv"] {
        assert!(!libs.contains(lib), "{bin} links {lib}:\n{libs}");
    }
}
