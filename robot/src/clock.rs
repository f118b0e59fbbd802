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
        }
    )*};
}
forward_clock!(Arc<T>, Box<T>, &T);

/// A simulated clock. Clones share one time; nothing moves it but [`SimClock::advance`],
/// [`SimClock::set`] and [`Clock::sleep`].
#[derive(Clone, Debug, Default)]
pub struct SimClock {
    nanos: Arc<AtomicU64>,
}

impl SimClock {
    /// A clock at time zero.
    pub fn new() -> Self {
        Self::default()
    }

    /// Move time forward by `d` (saturating at about 584 years).
    pub fn advance(&self, d: Duration) {
        let add = u64::try_from(d.as_nanos()).unwrap_or(u64::MAX);
        // fetch_update with a closure that always returns Some cannot fail.
        let _ = self
            .nanos
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| {
                Some(n.saturating_add(add))
            });
    }

    /// Set the time.
    pub fn set(&self, t: Duration) {
        self.nanos.store(
            u64::try_from(t.as_nanos()).unwrap_or(u64::MAX),
            Ordering::SeqCst,
        );
    }
}

impl Clock for SimClock {
    fn now(&self) -> Duration {
        Duration::from_nanos(self.nanos.load(Ordering::SeqCst))
    }

    fn sleep(&self, d: Duration) {
        self.advance(d);
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
    fn the_wall_clock_moves_forward() {
        let c = WallClock::new();
        let t0 = c.now();
        c.sleep(Duration::from_millis(2));
        assert!(c.now() >= t0 + Duration::from_millis(2));
    }
}
