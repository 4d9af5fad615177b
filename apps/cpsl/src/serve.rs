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
