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
        let listener = listen(a.addr).with_context(|| format!("cannot listen on {}", a.addr))?;
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

/// A listening socket with a deep accept queue, so that a burst of clients arriving together
/// is queued rather than dropped (and retried a second later).
fn listen(addr: SocketAddr) -> std::io::Result<tokio::net::TcpListener> {
    let socket = match addr {
        SocketAddr::V4(_) => tokio::net::TcpSocket::new_v4()?,
        SocketAddr::V6(_) => tokio::net::TcpSocket::new_v6()?,
    };
    socket.set_reuseaddr(true)?;
    socket.bind(addr)?;
    socket.listen(4096)
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
    /// Also load another server that serves the same folder at its root (e.g. nginx on
    /// `127.0.0.1:8081`, files under `/files/` mapped to the folder), right after ours, and
    /// report both side by side.
    #[arg(long)]
    pub peer: Option<SocketAddr>,
    /// Write the report(s) as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// Starts `cpsl serve DIR` on an ephemeral loopback port in its own process (as the peer
/// runs in its own), and loads it with `clients` clients.
pub fn bench(a: BenchServeArgs) -> anyhow::Result<()> {
    use std::io::BufRead;
    anyhow::ensure!(a.clients >= 1, "--clients must be at least 1");
    anyhow::ensure!(
        a.seconds > 0.0 && a.seconds.is_finite(),
        "--seconds must be positive"
    );
    let root = std::fs::canonicalize(&a.dir)
        .with_context(|| format!("cannot serve {}", a.dir.display()))?;
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
    let mut child = std::process::Command::new(std::env::current_exe()?)
        .arg("serve")
        .arg(&root)
        .args(["--addr", "127.0.0.1:0"])
        .stdout(std::process::Stdio::piped())
        .spawn()
        .context("starting `cpsl serve`")?;
    let mut first = String::new();
    std::io::BufReader::new(child.stdout.take().context("server output")?).read_line(&mut first)?;
    let addr: SocketAddr = first
        .split("http://")
        .nth(1)
        .and_then(|s| s.trim().trim_end_matches('/').parse().ok())
        .with_context(|| format!("unexpected server output: {first}"))?;
    eprintln!(
        "{} clients fetching {} files of {} package(s) from http://{addr}/ for {} s",
        a.clients,
        paths.len(),
        listing.packages.len(),
        a.seconds
    );
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let load = |addr| cpsl_server::LoadConfig {
        addr,
        paths: paths.clone(),
        clients: a.clients,
        duration: Duration::from_secs_f64(a.seconds),
    };
    let ours = rt.block_on(cpsl_server::run_load(&load(addr)));
    let _ = child.kill();
    let _ = child.wait();
    let peer = a.peer.map(|p| {
        eprintln!("the same load on the peer at http://{p}/");
        rt.block_on(cpsl_server::run_load(&load(p)))
    });
    let report = (ours, peer);
    let line = |name: &str, r: &cpsl_server::LoadReport| {
        println!(
            "{name:>6}: {} requests in {:.1} s: {:.0} requests/s, {:.1} MB/s; latency p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms; {} errors",
            r.requests,
            r.seconds,
            r.requests_per_second,
            r.megabytes_per_second,
            r.p50_ms,
            r.p99_ms,
            r.max_ms,
            r.errors
        )
    };
    let (ours, peer) = report;
    line("cpsl", &ours);
    if let Some(p) = &peer {
        line("peer", p);
        println!(
            "cpsl / peer: {:.2}x the requests per second, {:.2}x the p99 latency",
            ours.requests_per_second / p.requests_per_second.max(1e-9),
            ours.p99_ms / p.p99_ms.max(1e-9)
        );
    }
    if let Some(p) = &a.json {
        let v = serde_json::json!({ "cpsl": ours, "peer": peer });
        std::fs::write(p, serde_json::to_string_pretty(&v)?)?;
    }
    anyhow::ensure!(ours.errors == 0, "{} requests failed", ours.errors);
    Ok(())
}
