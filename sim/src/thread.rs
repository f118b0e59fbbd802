//! The suture thread: lengths and a shape. Its tail is anchored at the first stitch (a knot
//! beside the first entry before any); every suture holds some thread tight and, until
//! cinched, a loop of slack; the rest is free, running from the anchor (the last stitch's
//! exit) to the needle's swage. The free thread lies as a polyline: straight when taut, else
//! sagging onto the tissue to one side, the side drawn when the needle goes through (the
//! seed's `Thread` stream). Where it lies decides, by distance, whether it hides the needle,
//! whether a closing jaw catches it, and whether a sweep's open jaw pushes it away.

use crate::SimError;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use stitch_robot::{Point, Vector};

/// The thread model's parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ThreadConfig {
    /// Thread length at the start (the paper's threads: 10–40 cm), m.
    pub length_m: f64,
    /// Thread one tight suture holds (physical: the bite plus the run to the previous
    /// stitch; modelling choice 2 cm), m.
    pub per_suture_m: f64,
    /// Slack a new suture's loop holds until it is cinched (modelling choice 3 cm), m.
    pub loop_per_suture_m: f64,
    /// Free thread the needle needs to make the next throw (modelling choice 5 cm), m.
    pub reach_m: f64,
    /// Of the free thread, how much lies near the wound (the rest trails away out of reach:
    /// modelling choice 6 cm), m.
    pub near_m: f64,
    /// A closing jaw catches thread lying within this distance of its tip (modelling choice:
    /// 2 mm, about the jaw's half-width), m.
    pub catch_radius_m: f64,
    /// Thread within this distance of the needle's tip or centre hides it from the camera
    /// (modelling choice), m.
    pub occlusion_radius_m: f64,
    /// Half the width of the corridor a sweep's open jaw clears (60° open, 9 mm blades:
    /// about 4.5 mm; modelling choice 5 mm), m.
    pub sweep_half_width_m: f64,
    /// Chance that a cinch tangles the thread around a jaw (modelling choice).
    pub p_tangle_per_cinch: f64,
}

impl Default for ThreadConfig {
    fn default() -> Self {
        Self {
            length_m: 0.30,
            per_suture_m: 0.02,
            loop_per_suture_m: 0.03,
            reach_m: 0.05,
            near_m: 0.06,
            catch_radius_m: 0.002,
            occlusion_radius_m: 0.004,
            sweep_half_width_m: 0.005,
            p_tangle_per_cinch: 0.02,
        }
    }
}

impl ThreadConfig {
    /// Refuse parameters no thread has.
    pub fn validate(&self) -> Result<(), SimError> {
        let bad = |what: &str, v: f64, range: &str| {
            Err(SimError::Config {
                what: format!("thread.{what}"),
                why: format!("{v}; expected {range}"),
            })
        };
        if !(self.length_m.is_finite() && (0.05..=1.0).contains(&self.length_m)) {
            return bad("length_m", self.length_m, "0.05 to 1.0 m");
        }
        for (name, v) in [
            ("per_suture_m", self.per_suture_m),
            ("loop_per_suture_m", self.loop_per_suture_m),
            ("reach_m", self.reach_m),
            ("near_m", self.near_m),
            ("catch_radius_m", self.catch_radius_m),
            ("occlusion_radius_m", self.occlusion_radius_m),
            ("sweep_half_width_m", self.sweep_half_width_m),
        ] {
            if !(v.is_finite() && (0.0..=0.2).contains(&v)) {
                return bad(name, v, "0 to 0.2 m");
            }
        }
        if !(self.p_tangle_per_cinch.is_finite() && (0.0..=1.0).contains(&self.p_tangle_per_cinch))
        {
            return bad(
                "p_tangle_per_cinch",
                self.p_tangle_per_cinch,
                "a probability, 0 to 1",
            );
        }
        Ok(())
    }
}

/// The thread's state.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Thread {
    /// Its parameters.
    pub config: ThreadConfig,
    /// Thread held tight in sutures, m.
    pub used_m: f64,
    /// Slack in the sutures' loops, m.
    pub loop_m: f64,
    /// Where the free thread leaves the suture line, m.
    pub anchor: Point,
    /// The tissue's top surface, where slack comes to rest (z, m).
    pub surface_z: f64,
    /// Horizontal direction the slack falls to.
    pub sag_dir: Vector,
    /// A sweep pushed the slack to at least this y, until the next throw, m.
    pub pushed_to_y: Option<f64>,
    /// Where the free thread near the wound lies: anchor, sag, swage, m.
    pub polyline: Vec<Point>,
    /// Whether a jaw holds it (with or without the needle).
    pub caught: bool,
    /// Whether it is tangled around a jaw.
    pub tangled: bool,
    /// Whether too little is free for the throw under way.
    pub short: bool,
}

/// Distance from `p` to the segment `a`–`b`, m.
fn to_segment(p: &Point, a: &Point, b: &Point) -> f64 {
    let ab = b - a;
    let t = if ab.norm_squared() > 0.0 {
        ((p - a).dot(&ab) / ab.norm_squared()).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (p - (a + ab * t)).norm()
}

impl Thread {
    /// A fresh thread, all of it free, its tail at `anchor`, slack resting at `surface_z`.
    pub fn new(config: ThreadConfig, anchor: Point, surface_z: f64) -> Result<Self, SimError> {
        config.validate()?;
        Ok(Self {
            config,
            used_m: 0.0,
            loop_m: 0.0,
            anchor,
            surface_z,
            sag_dir: -Vector::y(),
            pushed_to_y: None,
            polyline: vec![anchor, anchor],
            caught: false,
            tangled: false,
            short: false,
        })
    }

    /// Free thread on the needle's side, m.
    pub fn remaining_m(&self) -> f64 {
        self.config.length_m - self.used_m - self.loop_m
    }

    /// Lay the free thread from the anchor to the needle's swage at `swage`: straight if the
    /// near part is taut, else through a sag point on the tissue, offset along `sag_dir` so
    /// the polyline has the near part's length.
    pub fn lay(&mut self, swage: Point) {
        let a = self.anchor;
        let length = self.remaining_m().min(self.config.near_m).max(0.0);
        let chord = (swage - a).norm();
        if length <= chord + 1e-9 {
            self.polyline = vec![a, swage];
            return;
        }
        let mid = Point::from((a.coords + swage.coords) / 2.0);
        let rest = Point::new(mid.x, mid.y, self.surface_z.min(mid.z));
        let through = |m: &Point| (m - a).norm() + (swage - m).norm();
        let mut m = if through(&rest) >= length {
            // Dropping to the tissue is already enough: hang part way down.
            let (mut lo, mut hi) = (0.0, 1.0);
            for _ in 0..50 {
                let t = (lo + hi) / 2.0;
                if through(&(mid + (rest - mid) * t)) < length {
                    lo = t
                } else {
                    hi = t
                }
            }
            mid + (rest - mid) * lo
        } else {
            let (mut lo, mut hi) = (0.0, length);
            for _ in 0..60 {
                let d = (lo + hi) / 2.0;
                if through(&(rest + self.sag_dir * d)) < length {
                    lo = d
                } else {
                    hi = d
                }
            }
            rest + self.sag_dir * lo
        };
        if let Some(y) = self.pushed_to_y {
            m.y = m.y.max(y);
        }
        self.polyline = vec![a, m, swage];
    }

    /// The distance from `p` to the free thread near the wound, m.
    pub fn distance_to(&self, p: &Point) -> f64 {
        self.polyline
            .windows(2)
            .map(|w| to_segment(p, &w[0], &w[1]))
            .fold(f64::INFINITY, f64::min)
    }

    /// Whether the thread hides a needle with this centre and tip.
    pub fn occludes(&self, center: &Point, tip: &Point) -> bool {
        let r = self.config.occlusion_radius_m;
        self.distance_to(center) <= r || self.distance_to(tip) <= r
    }

    /// A needle went through the tissue: one more suture holds thread, with a loop of slack;
    /// the free thread's slack falls to a side drawn from `rng`. If less than the reach is
    /// left free, the thread is short.
    pub fn on_insertion(&mut self, rng: &mut ChaCha8Rng) {
        self.used_m += self.config.per_suture_m;
        self.loop_m += self.config.loop_per_suture_m;
        // A micrometre of slack for rounding: lengths are sums of centimetres.
        if self.remaining_m() < self.config.reach_m - 1e-6 {
            self.short = true;
        }
        let angle = rng.random_range(0.0..std::f64::consts::TAU);
        self.sag_dir = Vector::new(angle.cos(), angle.sin(), 0.0);
        self.pushed_to_y = None;
    }

    /// The needle came out through `exit`: the free thread now leaves the suture line there.
    pub fn on_extraction(&mut self, exit: Point) {
        self.anchor = Point::new(exit.x, exit.y, self.surface_z);
    }

    /// An open jaw swept along +y from `from` to `to_y`: thread lying in its corridor is
    /// pushed ahead of it, to `to_y`. Returns whether it moved any.
    pub fn on_sweep(&mut self, from: &Point, to_y: f64) -> bool {
        let hw = self.config.sweep_half_width_m;
        let caught_in_corridor = self
            .polyline
            .iter()
            .skip(1)
            .take(self.polyline.len().saturating_sub(2))
            .any(|p| {
                (p.x - from.x).abs() <= hw
                    && p.y >= from.y - hw
                    && p.y <= to_y
                    && p.z <= from.z + hw
            });
        if caught_in_corridor {
            self.pushed_to_y = Some(to_y);
        }
        caught_in_corridor
    }

    /// A jaw closed with its tip at `jaw_tip`: thread that close is caught.
    pub fn on_grasp(&mut self, jaw_tip: &Point) {
        if self.distance_to(jaw_tip) <= self.config.catch_radius_m {
            self.caught = true;
        }
    }

    /// A cinch pulled `beta_m` (β of "Suture Cinching"): as much slack as the loops hold
    /// comes out into the free length.
    pub fn on_cinch(&mut self, beta_m: f64, rng: &mut ChaCha8Rng) {
        let pulled = beta_m.max(0.0).min(self.loop_m);
        self.loop_m -= pulled;
        if rng.random_bool(self.config.p_tangle_per_cinch) {
            self.tangled = true;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Streams, Subsystem};

    fn thread() -> Thread {
        let c = ThreadConfig {
            p_tangle_per_cinch: 0.0,
            ..ThreadConfig::default()
        };
        Thread::new(c, Point::new(0.0, 0.0, 0.0), 0.0).expect("thread")
    }

    #[test]
    fn cinching_pulls_loop_slack_back_to_the_free_end() {
        let mut rng = Streams::new(1).rng(Subsystem::Thread);
        let mut t = thread();
        t.on_insertion(&mut rng);
        // 30 cm − 2 cm tight − 3 cm loop.
        assert!((t.remaining_m() - 0.25).abs() < 1e-12);
        t.on_cinch(0.12, &mut rng);
        // β = 12 cm pulls the whole 3 cm loop out, no more.
        assert!((t.remaining_m() - 0.28).abs() < 1e-12);
        assert!(!t.short);
    }

    #[test]
    fn without_cinching_the_sixth_throw_runs_short() {
        let mut rng = Streams::new(1).rng(Subsystem::Thread);
        let mut t = thread();
        for throw in 1..=6 {
            t.on_insertion(&mut rng);
            // Free: 30 − 5·throw cm; short once below the 5 cm reach.
            assert_eq!(
                t.short,
                throw == 6,
                "throw {throw}: {} m free",
                t.remaining_m()
            );
        }
        let mut t = thread();
        for _ in 1..=6 {
            t.on_insertion(&mut rng);
            t.on_cinch(0.03, &mut rng);
        }
        assert!(!t.short, "cinched every throw: 30 − 6·2 = 18 cm free");
        assert!((t.remaining_m() - 0.18).abs() < 1e-12);
    }

    #[test]
    fn slack_sags_to_its_side_with_the_near_length() {
        let mut t = thread();
        t.sag_dir = Vector::y();
        // Swage 2 cm from the anchor along x, 1 cm up; 6 cm of thread near the wound.
        t.lay(Point::new(0.02, 0.0, 0.01));
        let p = &t.polyline;
        assert_eq!(p.len(), 3);
        let length = (p[1] - p[0]).norm() + (p[2] - p[1]).norm();
        assert!((length - 0.06).abs() < 1e-9, "{length}");
        assert!(p[1].z.abs() < 1e-12, "resting on the tissue");
        assert!(p[1].y > 0.02, "fallen to +y");
        // Taut when the swage is farther than the near length.
        t.lay(Point::new(0.08, 0.0, 0.0));
        assert_eq!(t.polyline.len(), 2);
    }

    #[test]
    fn a_jaw_catches_thread_within_its_radius_and_a_sweep_pushes_it_away() {
        let mut t = thread();
        t.sag_dir = Vector::y();
        t.lay(Point::new(0.02, 0.0, 0.01));
        let sag = t.polyline[1];
        let mut far = t.clone();
        far.on_grasp(&(sag + Vector::new(0.0, 0.0, 0.005)));
        assert!(!far.caught, "5 mm away");
        t.clone().on_grasp(&(sag + Vector::new(0.0, 0.0, 0.001)));
        let mut near = t.clone();
        near.on_grasp(&(sag + Vector::new(0.0, 0.0, 0.001)));
        assert!(near.caught, "1 mm away");
        // A sweep along +y over the sag point pushes the slack ahead of it.
        let from = Point::new(sag.x, sag.y - 0.004, 0.004);
        assert!(t.on_sweep(&from, sag.y + 0.03));
        t.lay(Point::new(0.02, 0.0, 0.01));
        assert!(t.polyline[1].y >= sag.y + 0.03 - 1e-12);
        // One that passes 1 cm to the side misses it.
        let mut u = thread();
        u.sag_dir = Vector::y();
        u.lay(Point::new(0.02, 0.0, 0.01));
        assert!(!u.on_sweep(
            &Point::new(sag.x + 0.01, sag.y - 0.004, 0.004),
            sag.y + 0.03
        ));
    }

    #[test]
    fn bad_parameters_are_refused() {
        assert!(
            ThreadConfig {
                p_tangle_per_cinch: 1.5,
                ..ThreadConfig::default()
            }
            .validate()
            .is_err()
        );
        assert!(
            ThreadConfig {
                length_m: 2.0,
                ..ThreadConfig::default()
            }
            .validate()
            .is_err()
        );
    }
}
