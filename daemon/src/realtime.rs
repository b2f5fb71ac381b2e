//! The presenting thread ahead of the renderer: real-time scheduling (`SCHED_FIFO`) for the one
//! thread that waits for a swap's present time and presents, and optionally a core of its own.
//!
//! A thread that only sleeps until its time, spins at most [`crate::presenter::PreciseWait`]'s
//! 500 us, and presents, is what real-time priority is for (audio servers, chrony and ptp4l run
//! theirs so): when its sleep ends it takes a core from the renders at once, where a normal
//! thread waits for the scheduler (3.6-5.3 ms late at p99 on a node whose cores the renders
//! fill, docs/swap.md). Nothing else runs real-time: a thread that renders would freeze the
//! machine. The kernel's real-time throttling stays on (`/proc/sys/kernel/sched_rt_runtime_us`:
//! real-time threads get at most 95% of a core's time by default), so even a present that spun
//! in a driver would leave the machine its share.
//!
//! Where the process may not (no `CAP_SYS_NICE`, no `RLIMIT_RTPRIO`: systemd's `LimitRTPRIO=`,
//! and `RestrictRealtime=no`), the node says so once, at start, with what to change, and presents
//! as before.

use thread_priority::{
    set_thread_priority_and_policy, thread_native_id, NormalThreadSchedulePolicy,
    RealtimeThreadSchedulePolicy, ThreadPriority, ThreadPriorityValue, ThreadSchedulePolicy,
};

const FIFO: ThreadSchedulePolicy = ThreadSchedulePolicy::Realtime(RealtimeThreadSchedulePolicy::Fifo);
const NORMAL: ThreadSchedulePolicy = ThreadSchedulePolicy::Normal(NormalThreadSchedulePolicy::Other);

/// What the presenting thread runs as (told to the controller in `NodeInfo`, shown by `up`, `orbit`
/// and the console beside the wake-up lateness).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PresentScheduling {
    /// `SCHED_FIFO` at this priority (and pinned to a core, where one was given).
    RealTime { priority: u8, cpu: Option<usize> },
    /// Normal scheduling: `present_priority = 0`.
    Off,
    /// Normal scheduling: real-time was asked for and refused, for this reason.
    Refused(String),
}

impl PresentScheduling {
    /// One line for the reports: `SCHED_FIFO 10`, `normal (off)`, `normal (refused: ...)`.
    pub fn describe(&self) -> String {
        match self {
            PresentScheduling::RealTime { priority, cpu: Some(c) } => {
                format!("SCHED_FIFO {priority} on core {c}")
            }
            PresentScheduling::RealTime { priority, cpu: None } => format!("SCHED_FIFO {priority}"),
            PresentScheduling::Off => "normal (present_priority = 0)".into(),
            PresentScheduling::Refused(why) => format!("normal (real-time refused: {why})"),
        }
    }
}

/// What to change where real-time scheduling is refused.
pub fn refused_advice(priority: u8) -> String {
    format!(
        "give the node's service `LimitRTPRIO={priority}` and `RestrictRealtime=no` (the packaged unit has both), \
         or run it with CAP_SYS_NICE; or set `present_priority = 0` to present with normal scheduling"
    )
}

/// Raises the calling thread to `SCHED_FIFO` at `priority` (1..=99).
pub fn raise(priority: u8) -> Result<(), String> {
    let value = ThreadPriorityValue::try_from(priority).map_err(|e| format!("priority {priority}: {e}"))?;
    set_thread_priority_and_policy(thread_native_id(), ThreadPriority::Crossplatform(value), FIFO)
        .map_err(|e| format!("SCHED_FIFO {priority}: {e:?}"))
}

/// Returns the calling thread to normal scheduling at nice value `nice` (its own before it was
/// raised: a thread may always keep or raise its nice value, not lower it).
pub fn lower(nice: i32) -> Result<(), String> {
    // The crate maps a 0..=99 value onto nice values for normal threads: the one that gives
    // `nice`, else the nearest higher nice (lower priority, always permitted).
    let to_nice = |p: u8| {
        let v = ThreadPriorityValue::try_from(p).ok()?;
        ThreadPriority::Crossplatform(v).to_posix(NORMAL).ok()
    };
    let p = (0..=99u8)
        .filter_map(|p| to_nice(p).map(|n| (p, n)))
        .filter(|&(_, n)| n >= nice)
        .min_by_key(|&(_, n)| n - nice)
        .map_or(0, |(p, _)| p);
    let value = ThreadPriorityValue::try_from(p).map_err(|e| e.to_string())?;
    set_thread_priority_and_policy(thread_native_id(), ThreadPriority::Crossplatform(value), NORMAL)
        .map_err(|e| format!("back to normal scheduling: {e:?}"))
}

/// The calling thread's nice value.
pub fn nice() -> i32 {
    rustix::process::getpriority_process(None).unwrap_or(0)
}

/// Pins the calling thread to core `cpu`.
pub fn pin_to(cpu: usize) -> Result<(), String> {
    let mut set = rustix::thread::CpuSet::new();
    set.set(cpu);
    rustix::thread::sched_setaffinity(None, &set).map_err(|e| format!("pinning to core {cpu}: {e}"))
}

/// Keeps the calling thread, and every thread it starts from now on, off core `cpu` (the render
/// thread and a software GPU's workers, where the presenting thread has that core).
pub fn keep_off(cpu: usize) -> Result<(), String> {
    let mut set = rustix::thread::sched_getaffinity(None).map_err(|e| format!("reading the cores: {e}"))?;
    if !set.is_set(cpu) {
        return Ok(());
    }
    set.unset(cpu);
    if set.count() == 0 {
        return Err(format!("core {cpu} is the only one this process may use"));
    }
    rustix::thread::sched_setaffinity(None, &set).map_err(|e| format!("keeping off core {cpu}: {e}"))
}

#[cfg(test)]
/// The scheduling policy of thread `tid` of process `pid` (`/proc/PID/task/TID/stat`'s 41st
/// field: 0 normal, 1 `SCHED_FIFO`, 2 `SCHED_RR`, ...).
pub fn policy_of(pid: u32, tid: u32) -> Option<u32> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/task/{tid}/stat")).ok()?;
    // The name (field 2) is in parentheses and may hold spaces: fields count from after it.
    let rest = stat.rsplit_once(')')?.1;
    rest.split_whitespace().nth(41 - 3).and_then(|f| f.parse().ok())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Where this process may use SCHED_FIFO (root here and in CI), a thread raised and lowered
    /// shows the policy in /proc, and its nice value survives the round trip.
    #[test]
    fn a_thread_raised_runs_fifo_and_lowered_keeps_its_nice_value() {
        let done = std::thread::spawn(|| {
            let _ = rustix::process::setpriority_process(None, 5);
            let before = nice();
            let tid = rustix::thread::gettid().as_raw_nonzero().get() as u32;
            let pid = std::process::id();
            if let Err(e) = raise(10) {
                assert!(std::env::var("CI").is_err(), "CI runs as root, where SCHED_FIFO is permitted: {e}");
                eprintln!("skipping: {e}");
                return;
            }
            assert_eq!(policy_of(pid, tid), Some(1), "SCHED_FIFO");
            lower(before).unwrap();
            assert_eq!(policy_of(pid, tid), Some(0), "normal again");
            assert_eq!(nice(), before, "its nice value kept");
        });
        done.join().unwrap();
    }

    #[test]
    fn the_reports_say_what_the_thread_runs_as() {
        assert_eq!(PresentScheduling::RealTime { priority: 10, cpu: None }.describe(), "SCHED_FIFO 10");
        assert!(PresentScheduling::Refused("EPERM".into()).describe().contains("refused: EPERM"));
        assert!(refused_advice(10).contains("LimitRTPRIO=10"));
    }
}
