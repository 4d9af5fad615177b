//! A bounded load generator for `cpsl bench serve`: `clients` kept-alive HTTP/1.1
//! connections, each fetching the given paths in turn for a fixed time; every response must be
//! a 200 whose body has its announced length.

use serde::Serialize;
use std::net::SocketAddr;
use std::time::{Duration, Instant};
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;

/// What to load.
#[derive(Debug, Clone)]
pub struct LoadConfig {
    /// The server.
    pub addr: SocketAddr,
    /// Request paths (e.g. every segment file of a package), fetched round-robin.
    pub paths: Vec<String>,
    /// Concurrent clients, one connection each.
    pub clients: usize,
    /// How long to run.
    pub duration: Duration,
}

/// The outcome.
#[derive(Debug, Clone, Default, Serialize)]
pub struct LoadReport {
    /// Clients.
    pub clients: usize,
    /// Seconds run.
    pub seconds: f64,
    /// Completed requests.
    pub requests: u64,
    /// Failed requests (connection errors, non-200 answers, short bodies).
    pub errors: u64,
    /// Body bytes received.
    pub bytes: u64,
    /// Requests per second.
    pub requests_per_second: f64,
    /// Body megabytes (10^6) per second.
    pub megabytes_per_second: f64,
    /// Median latency, milliseconds.
    pub p50_ms: f64,
    /// 99th percentile latency, milliseconds.
    pub p99_ms: f64,
    /// Worst latency, milliseconds.
    pub max_ms: f64,
}

async fn fetch(
    conn: &mut Option<BufReader<TcpStream>>,
    addr: SocketAddr,
    path: &str,
) -> std::io::Result<u64> {
    let bad = |m: String| std::io::Error::new(std::io::ErrorKind::InvalidData, m);
    if conn.is_none() {
        let s = TcpStream::connect(addr).await?;
        s.set_nodelay(true)?;
        *conn = Some(BufReader::new(s));
    }
    let c = conn.as_mut().expect("connected");
    c.get_mut()
        .write_all(format!("GET {path} HTTP/1.1\r\nHost: bench\r\n\r\n").as_bytes())
        .await?;
    let mut line = String::new();
    c.read_line(&mut line).await?;
    if !line.starts_with("HTTP/1.1 200") {
        return Err(bad(format!("{path}: {}", line.trim())));
    }
    let mut len = None;
    loop {
        line.clear();
        if c.read_line(&mut line).await? == 0 {
            return Err(bad("connection closed in the headers".into()));
        }
        let l = line.trim_end();
        if l.is_empty() {
            break;
        }
        if let Some((k, v)) = l.split_once(':') {
            if k.eq_ignore_ascii_case("content-length") {
                len = v.trim().parse::<u64>().ok();
            }
        }
    }
    let len = len.ok_or_else(|| bad("no content-length".into()))?;
    let got = tokio::io::copy(&mut c.take(len), &mut tokio::io::sink()).await?;
    if got != len {
        return Err(bad(format!("{got} of {len} bytes")));
    }
    Ok(len)
}

/// Runs the load and reports it.
pub async fn run_load(cfg: &LoadConfig) -> LoadReport {
    let start = Instant::now();
    let end = start + cfg.duration;
    let tasks: Vec<_> = (0..cfg.clients)
        .map(|c| {
            let paths = cfg.paths.clone();
            let addr = cfg.addr;
            tokio::spawn(async move {
                let mut conn = None;
                let (mut lat, mut errors, mut bytes) = (Vec::new(), 0u64, 0u64);
                let mut i = c;
                while Instant::now() < end && !paths.is_empty() {
                    let t = Instant::now();
                    match fetch(&mut conn, addr, &paths[i % paths.len()]).await {
                        Ok(n) => {
                            bytes += n;
                            lat.push(t.elapsed().as_secs_f64() * 1e3);
                        }
                        Err(e) => {
                            tracing::warn!("load client {c}: {e}");
                            errors += 1;
                            conn = None;
                        }
                    }
                    i += 1;
                }
                (lat, errors, bytes)
            })
        })
        .collect();
    let mut lat = Vec::new();
    let mut report = LoadReport {
        clients: cfg.clients,
        ..LoadReport::default()
    };
    for t in tasks {
        match t.await {
            Ok((l, e, b)) => {
                lat.extend(l);
                report.errors += e;
                report.bytes += b;
            }
            Err(_) => report.errors += 1,
        }
    }
    report.seconds = start.elapsed().as_secs_f64();
    report.requests = lat.len() as u64;
    lat.sort_by(f64::total_cmp);
    let pct = |p: f64| {
        lat.get(((lat.len() as f64 - 1.0) * p).round() as usize)
            .copied()
            .unwrap_or(0.0)
    };
    report.p50_ms = pct(0.5);
    report.p99_ms = pct(0.99);
    report.max_ms = lat.last().copied().unwrap_or(0.0);
    report.requests_per_second = report.requests as f64 / report.seconds;
    report.megabytes_per_second = report.bytes as f64 / 1e6 / report.seconds;
    report
}
