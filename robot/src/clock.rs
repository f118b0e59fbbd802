//! Time, injected: a simulated clock that tests and simulations advance, and a wall clock.

use std::fmt::Debug;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// A source of time. Library code asks a `Clock`, never the system, so simulated runs are
/// exact and repeatable.
pub trait Clock: Send + Sync + Debug {
    /// Time since the clock's epoch (the start of the run).
    fn now(&self) -> Duration;
    /// Wait `d`. A simulated clock advances itself by `d` instead of blocking.
    fn sleep(&self, d: Duration);
    /// How fast this clock runs against the wall clock: 1 for the wall clock, the pace of a
    /// paced simulated clock, `None` for one that runs as fast as the simulation can.
    fn pace(&self) -> Option<f64> {
        None
    }
}

/// Forwards every call, so `Arc<dyn Clock>` (and `Box`, `&`) is a [`Clock`] too.
macro_rules! forward_clock {
    ($($ptr:ty),*) => {$(
        impl<T: Clock + ?Sized> Clock for $ptr {
            fn now(&self) -> Duration {
                (**self).now()
            }
            fn sleep(&self, d: Duration) {
                (**self).sleep(d)
            }
            fn pace(&self) -> Option<f64> {
                (**self).pace()
            }
        }
    )*};
}
forward_clock!(Arc<T>, Box<T>, &T);

/// A simulated clock. Clones share one time; nothing moves it but [`SimClock::advance`],
/// [`SimClock::set`] and [`Clock::sleep`]. A paced clock ([`SimClock::paced`]) also keeps
/// the wall clock from falling behind: advancing it waits until as much wall time has passed
/// (divided by the pace), so a person can watch and command a simulated run. The simulated
/// times, and so everything decided on them, are the same at any pace.
#[derive(Clone, Debug, Default)]
pub struct SimClock {
    nanos: Arc<AtomicU64>,
    pace: Option<Pace>,
}

/// A simulated clock's pace: simulated seconds per wall-clock second, from a wall epoch.
#[derive(Clone, Copy, Debug)]
struct Pace {
    per_wall_s: f64,
    epoch: Instant,
}

impl SimClock {
    /// A clock at time zero.
    pub fn new() -> Self {
        Self::default()
    }

    /// A clock at time zero that runs `pace` simulated seconds per wall-clock second (1.0:
    /// wall-clock speed). A pace that is not finite and positive runs as fast as it can.
    pub fn paced(pace: f64) -> Self {
        Self {
            nanos: Arc::default(),
            pace: (pace.is_finite() && pace > 0.0).then(|| Pace {
                per_wall_s: pace,
                epoch: Instant::now(),
            }),
        }
    }

    /// Wait, on a paced clock, until the wall clock has caught up with simulated time `t`.
    fn keep_pace(&self, t: Duration) {
        if let Some(p) = self.pace {
            let due = p.epoch + Duration::from_secs_f64(t.as_secs_f64() / p.per_wall_s);
            let now = Instant::now();
            if due > now {
                std::thread::sleep(due - now);
            }
        }
    }

    /// Move time forward by `d` (saturating at about 584 years).
    pub fn advance(&self, d: Duration) {
        let add = u64::try_from(d.as_nanos()).unwrap_or(u64::MAX);
        // fetch_update with a closure that always returns Some cannot fail.
        let before = self
            .nanos
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| {
                Some(n.saturating_add(add))
            })
            .unwrap_or_else(|n| n);
        self.keep_pace(Duration::from_nanos(before.saturating_add(add)));
    }

    /// Set the time.
    pub fn set(&self, t: Duration) {
        self.nanos.store(
            u64::try_from(t.as_nanos()).unwrap_or(u64::MAX),
            Ordering::SeqCst,
        );
        self.keep_pace(t);
    }
}

impl Clock for SimClock {
    fn now(&self) -> Duration {
        Duration::from_nanos(self.nanos.load(Ordering::SeqCst))
    }

    fn sleep(&self, d: Duration) {
        self.advance(d);
    }

    fn pace(&self) -> Option<f64> {
        self.pace.map(|p| p.per_wall_s)
    }
}

/// The real clock, for a real robot: time since construction.
#[derive(Debug)]
pub struct WallClock {
    epoch: Instant,
}

impl WallClock {
    /// A clock whose epoch is now.
    pub fn new() -> Self {
        Self {
            epoch: Instant::now(),
        }
    }
}

impl Default for WallClock {
    fn default() -> Self {
        Self::new()
    }
}

impl Clock for WallClock {
    fn now(&self) -> Duration {
        self.epoch.elapsed()
    }

    fn sleep(&self, d: Duration) {
        std::thread::sleep(d);
    }

    fn pace(&self) -> Option<f64> {
        Some(1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clones_share_one_time_and_sleep_advances_it() {
        let a = SimClock::new();
        let b = a.clone();
        a.advance(Duration::from_millis(1500));
        b.sleep(Duration::from_millis(500));
        assert_eq!(a.now(), Duration::from_secs(2));
        b.set(Duration::from_secs(7));
        assert_eq!(a.now(), Duration::from_secs(7));
    }

    #[test]
    fn a_paced_clock_keeps_simulated_time_and_waits_for_the_wall_clock() {
        let c = SimClock::paced(10.0);
        let wall = Instant::now();
        c.advance(Duration::from_millis(300));
        // 0.3 simulated seconds at ten times the wall clock's speed: 30 ms of wall time.
        assert_eq!(c.now(), Duration::from_millis(300));
        assert!(wall.elapsed() >= Duration::from_millis(30));
        assert_eq!(c.pace(), Some(10.0));
        assert_eq!(SimClock::new().pace(), None);
        assert_eq!(SimClock::paced(f64::NAN).pace(), None);
    }

    #[test]
    fn the_wall_clock_moves_forward() {
        let c = WallClock::new();
        let t0 = c.now();
        c.sleep(Duration::from_millis(2));
        assert!(c.now() >= t0 + Duration::from_millis(2));
    }
}
