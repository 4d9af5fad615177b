//! `cpsl serve`: packages and the browser player over HTTP (see `cpsl-server`).

use anyhow::Context;
use clap::Args;
use cpsl_server::{list_packages, router, serve, ServerConfig};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

/// Arguments of `cpsl serve`.
#[derive(Args)]
pub struct ServeArgs {
    /// Folder to serve: packages (from `cpsl encode` or `cpsl demo`) anywhere up to three
    /// folders deep, and `variants.json` sets.
    pub dir: PathBuf,
    /// Address to listen on (use 0.0.0.0:PORT to serve other machines).
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub addr: SocketAddr,
    /// Most requests handled at once.
    #[arg(long, default_value_t = 1024)]
    pub max_concurrent: usize,
}

pub fn run(a: ServeArgs) -> anyhow::Result<()> {
    let cfg = ServerConfig {
        max_concurrent: a.max_concurrent,
        ..ServerConfig::default()
    };
    let app = router(&a.dir, &cfg)?;
    let root = std::fs::canonicalize(&a.dir)?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind(a.addr)
            .await
            .with_context(|| format!("cannot listen on {}", a.addr))?;
        let addr = listener.local_addr()?;
        let listing = list_packages(&root);
        println!("serving {} on http://{addr}/", root.display());
        if listing.packages.is_empty() {
            println!("  no packages found yet (make one with `cpsl encode` or `cpsl demo`)");
        }
        for p in &listing.packages {
            println!(
                "  {}  {}x{}, {} frames, {}, {:.2} Mbit/s  ->  http://{addr}/?src={}",
                p.path,
                p.width,
                p.height,
                p.frames,
                p.codec,
                p.bitrate as f64 / 1e6,
                p.url
            );
        }
        for v in &listing.variant_sets {
            println!("  variants {v}  ->  http://{addr}/?src={v}");
        }
        println!("press Ctrl-C to stop");
        serve(
            listener,
            app,
            &cfg,
            shutdown_signal(),
            Duration::from_secs(10),
        )
        .await?;
        println!("stopped");
        anyhow::Ok(())
    })
}

/// Ctrl-C or SIGTERM.
async fn shutdown_signal() {
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    tokio::select! {
        _ = tokio::signal::ctrl_c() => {}
        _ = term => {}
    }
}

/// Arguments of `cpsl bench serve`.
#[derive(Args)]
pub struct BenchServeArgs {
    /// Folder of packages to serve (from `cpsl demo` or `cpsl encode`).
    #[arg(default_value = "out/demo")]
    pub dir: PathBuf,
    /// Concurrent clients (one kept-alive connection each).
    #[arg(long, default_value_t = 200)]
    pub clients: usize,
    /// Seconds to run.
    #[arg(long, default_value_t = 30.0)]
    pub seconds: f64,
    /// Write the report as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// Serves `dir` on an ephemeral loopback port and loads it with `clients` clients.
pub fn bench(a: BenchServeArgs) -> anyhow::Result<()> {
    anyhow::ensure!(a.clients >= 1, "--clients must be at least 1");
    anyhow::ensure!(
        a.seconds > 0.0 && a.seconds.is_finite(),
        "--seconds must be positive"
    );
    let cfg = ServerConfig::default();
    let app = router(&a.dir, &cfg)?;
    let root = std::fs::canonicalize(&a.dir)?;
    let listing = list_packages(&root);
    let paths: Vec<String> = listing
        .packages
        .iter()
        .flat_map(|p| cpsl_server::package_urls(&root, p))
        .collect();
    anyhow::ensure!(
        !paths.is_empty(),
        "no package under {} (make one with `cpsl demo`)",
        a.dir.display()
    );
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let report = rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let server = tokio::spawn(async move {
            let stop = async {
                let _ = rx.await;
            };
            serve(listener, app, &cfg, stop, Duration::from_secs(5)).await
        });
        eprintln!(
            "{} clients fetching {} files of {} package(s) from http://{addr}/ for {} s",
            a.clients,
            paths.len(),
            listing.packages.len(),
            a.seconds
        );
        let report = cpsl_server::run_load(&cpsl_server::LoadConfig {
            addr,
            paths,
            clients: a.clients,
            duration: Duration::from_secs_f64(a.seconds),
        })
        .await;
        let _ = tx.send(());
        server.await??;
        anyhow::Ok(report)
    })?;
    println!(
        "{} requests in {:.1} s: {:.0} requests/s, {:.1} MB/s; latency p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms; {} errors",
        report.requests,
        report.seconds,
        report.requests_per_second,
        report.megabytes_per_second,
        report.p50_ms,
        report.p99_ms,
        report.max_ms,
        report.errors
    );
    if let Some(p) = &a.json {
        std::fs::write(p, serde_json::to_string_pretty(&report)?)?;
    }
    anyhow::ensure!(report.errors == 0, "{} requests failed", report.errors);
    Ok(())
}
