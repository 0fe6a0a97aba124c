//! What every stage reports while it works: the counter of its steps and the log line an
//! expensive stage starts with.

/// The prefix of the info-level log line each expensive stage starts with (loading the images
/// for the network, extracting features): the tests of bad inputs check that no such line
/// precedes an error that needs no computation. (A checkpoint is loaded, and checked, before.)
pub const WORK_STARTS: &str = "stage: ";

/// Steps of a long stage reported from any thread (the CLI's progress bars; the learned
/// matcher's images and pairs take about half a second each).
pub trait StepCounter: Sync {
    /// A stage begins with `total` steps (0: not counted).
    fn stage(&self, _name: &str, _total: u64) {}
    /// One step of the current stage is done.
    fn step(&self) {}
}

/// Counts nothing.
#[derive(Debug, Clone, Copy, Default)]
pub struct NoCounter;

impl StepCounter for NoCounter {}
