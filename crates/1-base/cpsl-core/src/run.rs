//! What every benchmark report starts with and how it sums up frame times: the run's command
//! line, date, CPU and threads ([`RunInfo`]) and per-frame percentiles ([`Timing`]).

use serde::Serialize;

/// Where and when a benchmark ran: the command line, the date, the CPU and the worker
/// threads (the first fields of every report).
#[derive(Debug, Clone, Serialize)]
pub struct RunInfo {
    /// The command line that made the report.
    pub command: String,
    /// The date it was made.
    pub date: String,
    /// The CPU.
    pub cpu: String,
    /// Worker threads.
    pub threads: usize,
}

impl RunInfo {
    /// This process, now.
    pub fn now() -> Self {
        Self {
            command: std::env::args().collect::<Vec<_>>().join(" "),
            date: today(),
            cpu: cpu_name(),
            threads: rayon::current_num_threads(),
        }
    }
}

/// Today's date (UTC), `YYYY-MM-DD`.
pub fn today() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    civil_date(secs / 86_400)
}

/// The calendar date `days` after 1970-01-01 (Howard Hinnant's civil-from-days).
fn civil_date(days: u64) -> String {
    let z = days as i64 + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + (m <= 2) as i64;
    format!("{y:04}-{m:02}-{d:02}")
}

/// The CPU's model name from /proc/cpuinfo ("unknown" where it does not say).
pub fn cpu_name() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|v| v.trim().to_string())
        })
        .unwrap_or_else(|| "unknown".into())
}

/// The process's peak resident set (`VmHWM`), in KiB; 0 where /proc does not say.
pub fn peak_rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmHWM:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        })
        .unwrap_or(0)
}

/// Milliseconds per frame.
#[derive(Debug, Clone, Serialize)]
pub struct Timing {
    /// Median.
    pub median_ms: f64,
    /// 90th percentile.
    pub p90_ms: f64,
    /// 99th percentile.
    pub p99_ms: f64,
    /// Fastest.
    pub min_ms: f64,
    /// Slowest.
    pub max_ms: f64,
    /// Mean.
    pub mean_ms: f64,
}

impl Timing {
    /// Sums up per-frame milliseconds (at least one).
    ///
    /// # Panics
    /// When `ms` is empty.
    pub fn of(mut ms: Vec<f64>) -> Self {
        assert!(!ms.is_empty(), "Timing::of needs at least one time");
        ms.sort_by(f64::total_cmp);
        let n = ms.len();
        let at = |q: f64| ms[((n as f64 * q) as usize).min(n - 1)];
        Self {
            median_ms: if n % 2 == 1 {
                ms[n / 2]
            } else {
                (ms[n / 2 - 1] + ms[n / 2]) / 2.0
            },
            p90_ms: at(0.9),
            p99_ms: at(0.99),
            min_ms: ms[0],
            max_ms: ms[n - 1],
            mean_ms: ms.iter().sum::<f64>() / n as f64,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dates() {
        assert_eq!(civil_date(0), "1970-01-01");
        assert_eq!(civil_date(11_016), "2000-02-29");
        assert_eq!(civil_date(20_418), "2025-11-26");
    }

    #[test]
    fn percentiles() {
        let t = Timing::of((1..=100).rev().map(f64::from).collect());
        assert_eq!(t.median_ms, 50.5);
        assert_eq!(t.p90_ms, 91.0);
        assert_eq!(t.p99_ms, 100.0);
        assert_eq!((t.min_ms, t.max_ms), (1.0, 100.0));
        assert_eq!(t.mean_ms, 50.5);
        assert_eq!(Timing::of(vec![3.0]).median_ms, 3.0);
    }
}
