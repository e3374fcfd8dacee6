//! Errors of the core. The bindings map each variant onto a Python exception.

use std::fmt;

/// Everything that can go wrong in the core, in words a caller can act on.
#[derive(Debug, Clone, PartialEq)]
pub enum CoreError {
    /// A model file (or its bytes) is malformed, truncated or inconsistent.
    Format(String),
    /// An argument is out of range (shape, step size, tolerance, ...).
    Invalid(String),
    /// Reading a file failed.
    Io(String),
    /// A file that does not exist.
    NotFound(String),
    /// The memory a call needs is not there (or an allocation was refused): MemoryError in
    /// Python, never an abort.
    Memory(String),
}

impl fmt::Display for CoreError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            CoreError::Format(m) => write!(f, "invalid model file: {m}"),
            CoreError::Invalid(m) => write!(f, "{m}"),
            CoreError::Io(m) => write!(f, "i/o error: {m}"),
            CoreError::NotFound(m) => write!(f, "no such file: {m}"),
            CoreError::Memory(m) => write!(f, "{m}"),
        }
    }
}

impl std::error::Error for CoreError {}

/// Why a single step failed. A failed trajectory stops and reports this.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StepFailure {
    /// Newton did not meet its tolerance within the iteration cap.
    NotConverged,
    /// The Newton Jacobian was singular (or numerically so).
    SingularJacobian,
    /// A NaN or infinity appeared.
    NonFinite,
    /// The chart was evaluated beyond its domain (exponential chart at |x| near 2π).
    ChartSingular,
    /// The state left the domain of the structure (the open positive orthant of a
    /// log-canonical one).
    OutOfDomain,
}

impl StepFailure {
    /// A stable small integer code, used across the Python boundary.
    pub fn code(self) -> i8 {
        match self {
            StepFailure::NotConverged => 1,
            StepFailure::SingularJacobian => 2,
            StepFailure::NonFinite => 3,
            StepFailure::ChartSingular => 4,
            StepFailure::OutOfDomain => 5,
        }
    }

    pub fn describe(self) -> &'static str {
        match self {
            StepFailure::NotConverged => "Newton did not converge",
            StepFailure::SingularJacobian => "singular Newton Jacobian",
            StepFailure::NonFinite => "non-finite value",
            StepFailure::ChartSingular => "chart singular (|x| too close to 2*pi)",
            StepFailure::OutOfDomain => "left the domain (positive orthant)",
        }
    }
}
