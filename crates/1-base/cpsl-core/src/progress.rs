//! One typed event stream for long work: the CLI draws progress bars from it, other front
//! ends (viewer, server) can consume the same events. Non-fatal problems are warnings here,
//! never prints.

/// An event reported by long-running library code.
#[derive(Debug, Clone, PartialEq)]
pub enum ProgressEvent<'a> {
    /// A stage starts; `total` is the number of steps when known.
    Start {
        /// Stage name, e.g. `"render sweep"`.
        stage: &'a str,
        /// Number of steps, if known.
        total: Option<u64>,
    },
    /// `done` steps of the current stage are complete.
    Advance {
        /// Stage name.
        stage: &'a str,
        /// Steps done so far.
        done: u64,
    },
    /// A stage ends.
    Finish {
        /// Stage name.
        stage: &'a str,
    },
    /// Something non-fatal the user should know.
    Warning {
        /// Human-readable message.
        message: String,
    },
}

/// A sink for [`ProgressEvent`]s. Implementations must be cheap and thread-safe.
pub trait Progress: Sync {
    /// Receives one event.
    fn event(&self, event: ProgressEvent<'_>);
}

/// Discards every event.
#[derive(Debug, Default, Clone, Copy)]
pub struct NoProgress;

impl Progress for NoProgress {
    fn event(&self, _event: ProgressEvent<'_>) {}
}
