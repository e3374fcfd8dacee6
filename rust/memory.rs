//! Memory the core may take, and allocations that fail instead of aborting.
//!
//! An infallible allocation (`vec!`, `Vec::with_capacity`, `collect`) that the system refuses
//! aborts the whole process; under `ulimit -v` (RLIMIT_AS) the refusal is immediate, and under a
//! cgroup limit the kernel kills the process when the pages are touched. So every allocation
//! whose size a caller controls (batch sizes, layer widths from a file) goes through
//! [`try_filled`] / [`try_collect`], which turn a refusal into [`CoreError::Memory`], and the
//! large ones are checked first against [`usable_bytes`]: the least of what the machine, the
//! address-space limit and the cgroup leave to this process.

use std::path::Path;

use crate::error::CoreError;

/// The payload of a panic raised for refused memory where no `Result` can carry it (a workspace
/// made inside a thread pool, which hands the payload on unchanged): the bindings recognise it
/// by its type ([`out_of_memory`]) and raise MemoryError with its message. A type, not a
/// message prefix: no other panic, whatever its text, is taken for it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct OutOfMemory {
    /// What could not be allocated, in words for the user.
    pub message: String,
}

impl std::fmt::Display for OutOfMemory {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "out of memory: {}", self.message)
    }
}

/// Unwinds with an [`OutOfMemory`] payload carrying `error`'s text (the panic of an
/// infallible constructor whose allocation was refused).
pub fn panic_out_of_memory(error: &CoreError) -> ! {
    std::panic::panic_any(OutOfMemory {
        message: error.to_string(),
    })
}

/// The [`OutOfMemory`] a caught panic's payload is, if it is one.
pub fn out_of_memory(payload: &(dyn std::any::Any + Send)) -> Option<&OutOfMemory> {
    payload.downcast_ref::<OutOfMemory>()
}

/// Fraction of the usable memory one call may plan to take (the rest is headroom for Python,
/// NumPy and the allocator's own overhead).
pub const MEMORY_SHARE: f64 = 0.8;

/// A fixed number from a `/proc`-style "Key:   value kB" line, in bytes.
fn proc_kib(text: &str, key: &str) -> Option<usize> {
    let line = text.lines().find(|l| l.starts_with(key))?;
    let kib: usize = line[key.len()..].split_whitespace().next()?.parse().ok()?;
    kib.checked_mul(1024)
}

/// MemAvailable from /proc/meminfo.
fn mem_available() -> Option<usize> {
    proc_kib(
        &std::fs::read_to_string("/proc/meminfo").ok()?,
        "MemAvailable:",
    )
}

/// The soft RLIMIT_AS from /proc/self/limits ("Max address space  <soft> <hard> bytes"), minus
/// the address space already mapped (VmSize); None when unlimited or unreadable.
fn address_space_left() -> Option<usize> {
    let limits = std::fs::read_to_string("/proc/self/limits").ok()?;
    let line = limits
        .lines()
        .find(|l| l.starts_with("Max address space"))?;
    let soft = line["Max address space".len()..]
        .split_whitespace()
        .next()?;
    let limit: usize = soft.parse().ok()?; // "unlimited" does not parse: no limit
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let used = proc_kib(&status, "VmSize:").unwrap_or(0);
    Some(limit.saturating_sub(used))
}

/// A cgroup limit minus the cgroup's usage: v2 (`memory.max`, `memory.current`) or v1
/// (`memory.limit_in_bytes`, `memory.usage_in_bytes`); None when unlimited or unreadable.
fn cgroup_left() -> Option<usize> {
    let own = std::fs::read_to_string("/proc/self/cgroup").ok();
    cgroup_left_at(Path::new("/sys/fs/cgroup"), own.as_deref())
}

/// [`cgroup_left`] for a cgroup file system mounted at `root`, the process's
/// `/proc/self/cgroup` being `own`.
fn cgroup_left_at(root: &Path, own: Option<&str>) -> Option<usize> {
    let read = |p: &Path| std::fs::read_to_string(p).ok();
    let number = |s: String| s.trim().parse::<usize>().ok();
    // v2: the process's own cgroup ("0::/path") and each of its ancestors; the tightest wins.
    let own = own.and_then(|s| {
        s.lines()
            .find_map(|l| l.strip_prefix("0::").map(|p| p.trim().to_string()))
    });
    if let Some(own) = own {
        let mut best: Option<usize> = None;
        let mut found = false;
        let mut path = root.join(own.trim_start_matches('/'));
        loop {
            if let Some(max) = read(&path.join("memory.max")) {
                found = true;
                // "max": no limit at this level.
                if let Some(limit) = number(max) {
                    let used = read(&path.join("memory.current"))
                        .and_then(number)
                        .unwrap_or(0);
                    let left = limit.saturating_sub(used);
                    best = Some(best.map_or(left, |b| b.min(left)));
                }
            }
            if path == root || !path.pop() {
                break;
            }
        }
        if found {
            return best;
        }
    }
    let dir = root.join("memory");
    let limit = read(&dir.join("memory.limit_in_bytes")).and_then(number)?;
    // v1 writes a huge number (close to i64::MAX, page-rounded) for "no limit".
    if limit >= 1 << 62 {
        return None;
    }
    let used = read(&dir.join("memory.usage_in_bytes"))
        .and_then(number)
        .unwrap_or(0);
    Some(limit.saturating_sub(used))
}

/// Bytes this process can still take: the least of MemAvailable, what RLIMIT_AS leaves of the
/// address space and what the cgroup's limit leaves; None where none of them can be read.
pub fn usable_bytes() -> Option<usize> {
    [mem_available(), address_space_left(), cgroup_left()]
        .into_iter()
        .flatten()
        .min()
}

/// Cap on one call where no limit can be read.
const FALLBACK_MAX_BYTES: usize = 16 << 30;

/// What one call may plan to take: [`MEMORY_SHARE`] of [`usable_bytes`].
pub fn budget_bytes() -> usize {
    usable_bytes()
        .map(|a| (a as f64 * MEMORY_SHARE) as usize)
        .unwrap_or(FALLBACK_MAX_BYTES)
}

fn gib(b: usize) -> f64 {
    b as f64 / f64::from(1u32 << 30)
}

/// Refuses, with [`CoreError::Memory`], a plan of `bytes` that would not fit in
/// [`budget_bytes`]; `what` says what the memory is for and `hint` how to need less.
pub fn check_fits(bytes: usize, what: &str, hint: &str) -> Result<(), CoreError> {
    let limit = budget_bytes();
    if bytes > limit {
        return Err(CoreError::Memory(format!(
            "{what} needs about {:.2} GiB but only {:.2} GiB can be used now (the least of the \
             available memory, the address-space limit and the cgroup limit); {hint}",
            gib(bytes),
            gib(limit)
        )));
    }
    Ok(())
}

fn refused<T>(len: usize, what: &str) -> CoreError {
    CoreError::Memory(format!(
        "cannot allocate {what} ({:.2} GiB)",
        gib(len.saturating_mul(std::mem::size_of::<T>()))
    ))
}

/// An empty vector with room for exactly `len` elements, or [`CoreError::Memory`].
pub fn try_with_capacity<T>(len: usize, what: &str) -> Result<Vec<T>, CoreError> {
    let mut v = Vec::new();
    v.try_reserve_exact(len)
        .map_err(|_| refused::<T>(len, what))?;
    Ok(v)
}

/// `vec![value; len]`, or [`CoreError::Memory`] where the allocation is refused.
pub fn try_filled<T: Clone>(len: usize, value: T, what: &str) -> Result<Vec<T>, CoreError> {
    let mut v = try_with_capacity(len, what)?;
    v.resize(len, value);
    Ok(v)
}

/// Collects an iterator of known length into a vector allocated fallibly.
pub fn try_collect<T>(
    len: usize,
    items: impl IntoIterator<Item = T>,
    what: &str,
) -> Result<Vec<T>, CoreError> {
    let mut v = try_with_capacity(len, what)?;
    v.extend(items.into_iter().take(len));
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn proc_lines_parse_to_bytes() {
        let text = "MemTotal:  100 kB\nMemAvailable:    2048 kB\n";
        assert_eq!(proc_kib(text, "MemAvailable:"), Some(2048 * 1024));
        assert_eq!(proc_kib(text, "Missing:"), None);
    }

    #[test]
    fn an_impossible_allocation_is_an_error_not_an_abort() {
        // More than any address space: the allocator refuses it at once.
        let e = try_filled(usize::MAX / 16, 0.0f64, "a test buffer").unwrap_err();
        assert!(
            matches!(e, CoreError::Memory(ref m) if m.contains("a test buffer")),
            "{e:?}"
        );
        assert!(check_fits(usize::MAX, "a test", "use less").is_err());
    }

    /// A refused allocation inside an infallible constructor unwinds with the typed payload,
    /// also out of a thread pool; a panic whose text merely looks like one is not taken for it.
    #[test]
    fn refused_memory_panics_with_a_typed_payload() {
        use rayon::prelude::*;
        use std::panic::{catch_unwind, AssertUnwindSafe};
        // A packed layer of 0.75 · usize::MAX numbers: the allocator refuses it at once.
        let direct = catch_unwind(|| crate::kernel::pack(&[], usize::MAX / 16, 7)).unwrap_err();
        let pooled = catch_unwind(|| {
            (0..64).into_par_iter().for_each(|i| {
                if i == 37 {
                    panic_out_of_memory(&CoreError::Memory("a pooled workspace".into()));
                }
            })
        })
        .unwrap_err();
        let forged =
            catch_unwind(AssertUnwindSafe(|| panic!("out of memory: not really"))).unwrap_err();
        let plain = catch_unwind(|| panic!("{}", "out of memory: a string")).unwrap_err();
        let oom = out_of_memory(&*direct).expect("the refused layer is an OutOfMemory");
        assert!(oom.message.contains("a packed layer"), "{oom}");
        let oom = out_of_memory(&*pooled).expect("the payload survives the pool");
        assert_eq!(oom.message, "a pooled workspace");
        assert_eq!(oom.to_string(), "out of memory: a pooled workspace");
        assert!(out_of_memory(&*forged).is_none());
        assert!(out_of_memory(&*plain).is_none());
    }

    /// A scratch folder laid out like a cgroup mount.
    fn fake_cgroup(name: &str, files: &[(&str, &str)]) -> std::path::PathBuf {
        let root =
            std::env::temp_dir().join(format!("poisson_rs_cgroup_{name}_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        for (path, text) in files {
            let p = root.join(path);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(p, text).unwrap();
        }
        root
    }

    #[test]
    fn cgroup_limits_are_read_v2_up_the_tree_and_v1() {
        let root = fake_cgroup(
            "v2",
            &[
                ("memory.max", "max\n"),
                ("a/memory.max", "1000000\n"),
                ("a/memory.current", "400000\n"),
                ("a/b/memory.max", "max\n"),
                ("a/b/memory.current", "10\n"),
            ],
        );
        // The parent's limit applies to the child: 1e6 - 4e5 left.
        assert_eq!(cgroup_left_at(&root, Some("0::/a/b\n")), Some(600_000));
        assert_eq!(cgroup_left_at(&root, Some("0::/\n")), None);
        let v1 = fake_cgroup(
            "v1",
            &[
                ("memory/memory.limit_in_bytes", "2000000\n"),
                ("memory/memory.usage_in_bytes", "500000\n"),
            ],
        );
        assert_eq!(cgroup_left_at(&v1, None), Some(1_500_000));
        let unlimited = fake_cgroup(
            "v1max",
            &[("memory/memory.limit_in_bytes", "9223372036854771712\n")],
        );
        assert_eq!(cgroup_left_at(&unlimited, None), None);
        for d in [root, v1, unlimited] {
            let _ = std::fs::remove_dir_all(d);
        }
    }

    #[test]
    fn the_budget_is_positive_and_below_the_machine() {
        let b = budget_bytes();
        assert!(b > 0);
        if let Some(avail) = mem_available() {
            assert!(b <= avail);
        }
    }
}
