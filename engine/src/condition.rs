//! Conditions a plan branches on: typed, decided by the runner at run time from what the
//! robot observes (a needle estimate, where the jaws are) and from the mission's own
//! bookkeeping (throw, interventions, retries, thread pulled) — never from a simulator's
//! hidden truth.
//!
//! A script builds them symbolically: `needle_confidence() >= 0.8` is not a number but a
//! [`Condition`], evaluated each time the plan reaches it. A comparison on a needle the
//! robot has never seen is false (there is no value to compare); `needle_seen()` says
//! whether the query saw it.

use serde::{Deserialize, Serialize};
use std::fmt;
use stitch_primitives::Observation;

/// A comparison.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Cmp {
    /// `<`
    Lt,
    /// `<=`
    Le,
    /// `>`
    Gt,
    /// `>=`
    Ge,
    /// `==` (whole-number quantities only)
    Eq,
    /// `!=` (whole-number quantities only)
    Ne,
}

impl Cmp {
    /// The operator as scripts write it.
    pub fn symbol(self) -> &'static str {
        match self {
            Cmp::Lt => "<",
            Cmp::Le => "<=",
            Cmp::Gt => ">",
            Cmp::Ge => ">=",
            Cmp::Eq => "==",
            Cmp::Ne => "!=",
        }
    }

    fn holds(self, a: f64, b: f64) -> bool {
        match self {
            Cmp::Lt => a < b,
            Cmp::Le => a <= b,
            Cmp::Gt => a > b,
            Cmp::Ge => a >= b,
            // Whole numbers only (validated when the script builds the condition).
            Cmp::Eq => (a - b).abs() < 0.5,
            Cmp::Ne => (a - b).abs() >= 0.5,
        }
    }
}

/// The kind of value a quantity has: what a script must compare it with.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Unit {
    /// A plain number (the estimator's confidence, 0 to 1).
    Number,
    /// A length, m (scripts write `mm(..)`, `cm(..)`, `m(..)`).
    Length,
    /// An angle, rad (`deg(..)`, `rad(..)`).
    Angle,
    /// A time, s (`s(..)`, `ms(..)`).
    Time,
    /// A whole number.
    Count,
}

impl Unit {
    /// What a script compares a quantity of this kind with, in words.
    pub fn expected(self) -> &'static str {
        match self {
            Unit::Number => "a number",
            Unit::Length => "a length, written mm(..), cm(..) or m(..)",
            Unit::Angle => "an angle, written deg(..) or rad(..)",
            Unit::Time => "a time, written s(..) or ms(..)",
            Unit::Count => "a whole number",
        }
    }
}

/// A place a needle end can be measured against.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Target {
    /// A point in the robot frame, m.
    Point([f64; 3]),
    /// The right (PSM1) jaw's tip, as the arm measures it.
    RightJaw,
    /// The left (PSM2) jaw's tip.
    LeftJaw,
    /// A point on the latest needle estimate's arc, this far along it from the tip towards
    /// the swage, rad: 0 is the tip, π the swage; π − 20° is where the handover's right jaw
    /// closes on a needle the left jaw holds by its tip (`docs/primitives.md`).
    NeedlePoint(f64),
}

impl fmt::Display for Target {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Target::Point([x, y, z]) => write!(
                f,
                "point(mm({:.1}), mm({:.1}), mm({:.1}))",
                x * 1e3,
                y * 1e3,
                z * 1e3
            ),
            Target::RightJaw => f.write_str("right_jaw()"),
            Target::LeftJaw => f.write_str("left_jaw()"),
            Target::NeedlePoint(a) => write!(f, "needle_point(deg({}))", round(a.to_degrees())),
        }
    }
}

/// Which end of the needle.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum End {
    /// The sharp tip.
    Tip,
    /// The swage, where the thread leaves.
    Swage,
}

/// A quantity a condition compares.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "of", rename_all = "snake_case")]
pub enum Quantity {
    /// The latest needle estimate's confidence, 0 to 1.
    NeedleConfidence,
    /// The angle between the latest estimate's normal and a direction (robot frame), rad.
    NeedleNormalAngle {
        /// The direction, a unit vector.
        to: [f64; 3],
    },
    /// The distance from a needle end (latest estimate) to a target, m.
    NeedleEndDistance {
        /// Which end.
        end: End,
        /// To what.
        to: Target,
    },
    /// How old the latest needle estimate is, s (infinite if there is none).
    NeedleAge,
    /// Thread left: the mission's `thread_length` less what the cinches pulled, m.
    ThreadLeft,
    /// How far the traced thread stays from a target, less twice its uncertainty where it
    /// comes nearest, m (negative: it may touch).
    ThreadClearance {
        /// From what.
        from: Target,
    },
    /// The traced thread's length from where it leaves the tissue to the swage, m.
    ThreadFree,
    /// How far the traced thread winds round the vertical through a target (its part
    /// within `WRAP_RADIUS_M` of it), rad: a full loop is 2π.
    ThreadWrap {
        /// Round what.
        round: Target,
    },
    /// The throw under way, 1-based.
    ThrowNumber,
    /// Interventions the robot may still ask for.
    InterventionsLeft,
    /// Retries the machine granted in this throw so far.
    RetriesUsed,
}

impl Quantity {
    /// The kind of value it has.
    pub fn unit(&self) -> Unit {
        match self {
            Quantity::NeedleConfidence => Unit::Number,
            Quantity::NeedleNormalAngle { .. } => Unit::Angle,
            Quantity::NeedleEndDistance { .. }
            | Quantity::ThreadLeft
            | Quantity::ThreadClearance { .. }
            | Quantity::ThreadFree => Unit::Length,
            Quantity::ThreadWrap { .. } => Unit::Angle,
            Quantity::NeedleAge => Unit::Time,
            Quantity::ThrowNumber | Quantity::InterventionsLeft | Quantity::RetriesUsed => {
                Unit::Count
            }
        }
    }

    /// Whether it is read from a needle query (a perception observation). A thread trace
    /// needs one too: it ends at the estimate's swage.
    pub fn needs_needle(&self) -> bool {
        matches!(
            self,
            Quantity::NeedleConfidence
                | Quantity::NeedleNormalAngle { .. }
                | Quantity::NeedleEndDistance { .. }
                | Quantity::NeedleAge
        ) || self.needs_thread()
    }

    /// Whether it is read from a thread trace.
    pub fn needs_thread(&self) -> bool {
        matches!(
            self,
            Quantity::ThreadClearance { .. } | Quantity::ThreadFree | Quantity::ThreadWrap { .. }
        )
    }

    /// The quantity as a script writes it.
    pub fn describe(&self) -> String {
        match self {
            Quantity::NeedleConfidence => "needle_confidence()".into(),
            Quantity::NeedleNormalAngle { to: [x, y, z] } => {
                format!("needle_normal_angle(direction({x}, {y}, {z}))")
            }
            Quantity::NeedleEndDistance { end, to } => format!(
                "needle_{}_distance({to})",
                match end {
                    End::Tip => "tip",
                    End::Swage => "swage",
                }
            ),
            Quantity::NeedleAge => "needle_age()".into(),
            Quantity::ThreadLeft => "thread_left()".into(),
            Quantity::ThreadClearance { from } => format!("thread_clearance({from})"),
            Quantity::ThreadFree => "thread_free()".into(),
            Quantity::ThreadWrap { round } => format!("thread_wrap({round})"),
            Quantity::ThrowNumber => "throw_number()".into(),
            Quantity::InterventionsLeft => "interventions_left()".into(),
            Quantity::RetriesUsed => "retries_used()".into(),
        }
    }

    fn bound(&self, v: f64) -> String {
        match self.unit() {
            Unit::Number => format!("{v}"),
            Unit::Length => format!("mm({})", round(v * 1e3)),
            Unit::Angle => format!("deg({})", round(v.to_degrees())),
            Unit::Time => format!("s({})", round(v)),
            Unit::Count => format!("{}", v.round() as i64),
        }
    }
}

fn round(v: f64) -> f64 {
    (v * 1e6).round() / 1e6
}

/// A condition a plan branches on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "if", rename_all = "snake_case")]
pub enum Condition {
    /// The needle query made for this condition saw the needle.
    NeedleSeen,
    /// A quantity compared with a bound (SI units: m, rad, s).
    Compare {
        /// What.
        quantity: Quantity,
        /// How.
        cmp: Cmp,
        /// With what.
        bound: f64,
    },
    /// Every one holds (true if empty).
    All {
        /// The conditions.
        of: Vec<Condition>,
    },
    /// At least one holds (false if empty).
    Any {
        /// The conditions.
        of: Vec<Condition>,
    },
    /// It does not hold.
    Not {
        /// The condition.
        of: Box<Condition>,
    },
}

/// What the engine itself knows when a condition is decided.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MissionFacts {
    /// The throw under way, 1-based.
    pub throw_number: usize,
    /// Interventions the robot may still ask for.
    pub interventions_left: u8,
    /// Retries granted in this throw so far.
    pub retries_used: u8,
    /// The mission's thread length less what the cinches pulled, m; `None` if the plan gives
    /// no thread length.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub thread_left_m: Option<f64>,
}

/// What a condition was decided on: the observation (if a query ran), the time, the facts.
#[derive(Clone, Copy, Debug)]
pub struct Facts<'a> {
    /// What the robot observed for this condition.
    pub observation: &'a Observation,
    /// The run's clock when it was decided, s.
    pub now_s: f64,
    /// The engine's bookkeeping.
    pub mission: MissionFacts,
}

impl Condition {
    /// Its terms: leaves and combinators, counted (saturating).
    pub fn terms(&self) -> usize {
        match self {
            Condition::NeedleSeen | Condition::Compare { .. } => 1,
            Condition::All { of } | Condition::Any { of } => {
                of.iter().fold(1usize, |n, c| n.saturating_add(c.terms()))
            }
            Condition::Not { of } => of.terms().saturating_add(1),
        }
    }

    /// Whether deciding it needs a thread trace.
    pub fn needs_thread(&self) -> bool {
        match self {
            Condition::NeedleSeen => false,
            Condition::Compare { quantity, .. } => quantity.needs_thread(),
            Condition::All { of } | Condition::Any { of } => of.iter().any(Self::needs_thread),
            Condition::Not { of } => of.needs_thread(),
        }
    }

    /// Whether deciding it needs a needle query.
    pub fn needs_needle(&self) -> bool {
        match self {
            Condition::NeedleSeen => true,
            Condition::Compare { quantity, .. } => quantity.needs_needle(),
            Condition::All { of } | Condition::Any { of } => of.iter().any(Self::needs_needle),
            Condition::Not { of } => of.needs_needle(),
        }
    }

    /// Whether any part reads `q`'s kind of quantity (compared by variant).
    pub fn reads(&self, q: &Quantity) -> bool {
        match self {
            Condition::NeedleSeen => false,
            Condition::Compare { quantity, .. } => {
                std::mem::discriminant(quantity) == std::mem::discriminant(q)
            }
            Condition::All { of } | Condition::Any { of } => of.iter().any(|c| c.reads(q)),
            Condition::Not { of } => of.reads(q),
        }
    }

    /// Decide it.
    pub fn eval(&self, f: &Facts<'_>) -> bool {
        match self {
            Condition::NeedleSeen => f.observation.needle_now,
            Condition::Compare {
                quantity,
                cmp,
                bound,
            } => value(quantity, f).is_some_and(|v| cmp.holds(v, *bound)),
            Condition::All { of } => of.iter().all(|c| c.eval(f)),
            Condition::Any { of } => of.iter().any(|c| c.eval(f)),
            Condition::Not { of } => !of.eval(f),
        }
    }

    /// Decide it from the engine's facts alone, where they settle it (`None` where it
    /// depends on what the robot observes): the model checker branches only on the rest.
    pub fn eval_known(&self, m: &MissionFacts) -> Option<bool> {
        match self {
            Condition::NeedleSeen => None,
            Condition::Compare {
                quantity,
                cmp,
                bound,
            } => mission_value(quantity, m).map(|v| v.is_some_and(|v| cmp.holds(v, *bound))),
            Condition::All { of } => known_fold(of, m, false),
            Condition::Any { of } => known_fold(of, m, true),
            Condition::Not { of } => of.eval_known(m).map(|v| !v),
        }
    }
}

/// `all` (`decisive` false) or `any` (`decisive` true) in three values: the decisive value
/// if any term has it, else unknown if any term is, else the other value.
fn known_fold(of: &[Condition], m: &MissionFacts, decisive: bool) -> Option<bool> {
    let mut value = Some(!decisive);
    for c in of {
        match c.eval_known(m) {
            Some(v) if v == decisive => return Some(decisive),
            None => value = None,
            Some(_) => {}
        }
    }
    value
}

/// The value of a mission quantity (`Some(None)`: known to have no value), or `None` for a
/// quantity read from observations.
fn mission_value(q: &Quantity, m: &MissionFacts) -> Option<Option<f64>> {
    Some(match q {
        Quantity::ThreadLeft => m.thread_left_m,
        Quantity::ThrowNumber => Some(m.throw_number as f64),
        Quantity::InterventionsLeft => Some(f64::from(m.interventions_left)),
        Quantity::RetriesUsed => Some(f64::from(m.retries_used)),
        _ => return None,
    })
}

/// Where a target is now: a point, or a jaw's measured tip (`None` if its arm did not say).
fn target(to: &Target, f: &Facts<'_>) -> Option<stitch_robot::Point> {
    match to {
        Target::Point(p) => Some(stitch_robot::Point::new(p[0], p[1], p[2])),
        Target::RightJaw => f.observation.right_jaw,
        Target::LeftJaw => f.observation.left_jaw,
        Target::NeedlePoint(a) => {
            // The needle's frame has the tip at angle 0 and the arc turning about its normal
            // (robot::Needle::point_at): rotate the centre-to-tip radius by `a`.
            let n = f.observation.needle.as_ref()?;
            let r = n.tip - n.center;
            Some(n.center + r * a.cos() + n.normal.normalize().cross(&r) * a.sin())
        }
    }
}

/// The part of the thread within this distance of a target is what winds round it, m.
pub const WRAP_RADIUS_M: f64 = 0.03;

/// The least distance from `at` to the polyline less twice the uncertainty there, m.
fn clearance(
    points: &[stitch_robot::Point],
    sigma_m: &[f64],
    at: &stitch_robot::Point,
) -> Option<f64> {
    let sigma = |i: usize| sigma_m.get(i).copied().unwrap_or(0.0);
    let mut best: Option<f64> = None;
    let mut keep = |d: f64| best = Some(best.map_or(d, |b: f64| b.min(d)));
    if let [only] = points {
        keep((only - at).norm() - 2.0 * sigma(0));
    }
    for (i, w) in points.windows(2).enumerate() {
        let (q, s) = stitch_robot::nearest_on_segment(at, &w[0], &w[1]);
        keep((q - at).norm() - 2.0 * (sigma(i) * (1.0 - s) + sigma(i + 1) * s));
    }
    best
}

/// How far the polyline winds round the vertical (robot z) through `at`, over its steps
/// with both ends within `WRAP_RADIUS_M` of it, rad (absolute).
fn wrap(points: &[stitch_robot::Point], at: &stitch_robot::Point) -> f64 {
    let near = |p: &stitch_robot::Point| (p - at).norm() <= WRAP_RADIUS_M;
    let angle = |p: &stitch_robot::Point| (p.y - at.y).atan2(p.x - at.x);
    let mut total = 0.0;
    for w in points.windows(2) {
        if near(&w[0]) && near(&w[1]) {
            let mut d = angle(&w[1]) - angle(&w[0]);
            while d > std::f64::consts::PI {
                d -= std::f64::consts::TAU;
            }
            while d < -std::f64::consts::PI {
                d += std::f64::consts::TAU;
            }
            total += d;
        }
    }
    total.abs()
}

fn value(q: &Quantity, f: &Facts<'_>) -> Option<f64> {
    if let Some(v) = mission_value(q, &f.mission) {
        return v;
    }
    let seen = f.observation.needle.as_ref();
    match q {
        Quantity::NeedleAge => Some(seen.map_or(f64::INFINITY, |n| (f.now_s - n.stamp_s).max(0.0))),
        Quantity::NeedleConfidence => seen.map(|n| n.confidence),
        Quantity::NeedleNormalAngle { to } => seen.map(|n| {
            let d = stitch_robot::Vector::new(to[0], to[1], to[2]);
            n.normal.angle(&d)
        }),
        Quantity::NeedleEndDistance { end, to } => {
            let n = seen?;
            let from = match end {
                End::Tip => n.tip,
                End::Swage => n.swage,
            };
            Some((from - target(to, f)?).norm())
        }
        Quantity::ThreadFree => f.observation.thread.as_ref().map(|t| t.length_m),
        Quantity::ThreadClearance { from } => {
            let t = f.observation.thread.as_ref()?;
            let at = target(from, f)?;
            clearance(&t.points, &t.sigma_m, &at)
        }
        Quantity::ThreadWrap { round } => {
            let t = f.observation.thread.as_ref()?;
            Some(wrap(&t.points, &target(round, f)?))
        }
        _ => None,
    }
}

impl fmt::Display for Condition {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Condition::NeedleSeen => f.write_str("needle_seen()"),
            Condition::Compare {
                quantity,
                cmp,
                bound,
            } => write!(
                f,
                "{} {} {}",
                quantity.describe(),
                cmp.symbol(),
                quantity.bound(*bound)
            ),
            Condition::All { of } | Condition::Any { of } => {
                f.write_str(if matches!(self, Condition::All { .. }) {
                    "all(["
                } else {
                    "any(["
                })?;
                for (i, c) in of.iter().enumerate() {
                    if i > 0 {
                        f.write_str(", ")?;
                    }
                    write!(f, "{c}")?;
                }
                f.write_str("])")
            }
            Condition::Not { of } => write!(f, "not({of})"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use stitch_primitives::NeedleSeen;
    use stitch_robot::{Point, Vector};

    fn facts(obs: &Observation) -> Facts<'_> {
        Facts {
            observation: obs,
            now_s: 10.0,
            mission: MissionFacts {
                throw_number: 2,
                interventions_left: 1,
                retries_used: 0,
                thread_left_m: None,
            },
        }
    }

    fn seen() -> Observation {
        Observation {
            needle: Some(NeedleSeen {
                center: Point::origin(),
                normal: Vector::y(),
                tip: Point::new(0.012, 0.0, 0.0),
                swage: Point::new(-0.012, 0.0, 0.0),
                confidence: 0.7,
                stamp_s: 9.0,
            }),
            needle_now: true,
            right_jaw: Some(Point::new(-0.012, 0.0, 0.002)),
            ..Observation::default()
        }
    }

    fn cmp(quantity: Quantity, cmp: Cmp, bound: f64) -> Condition {
        Condition::Compare {
            quantity,
            cmp,
            bound,
        }
    }

    #[test]
    fn needle_quantities_read_the_latest_estimate_and_are_false_without_one() {
        let obs = seen();
        let f = facts(&obs);
        assert!(cmp(Quantity::NeedleConfidence, Cmp::Lt, 0.8).eval(&f));
        assert!(!cmp(Quantity::NeedleConfidence, Cmp::Ge, 0.8).eval(&f));
        let angle = cmp(
            Quantity::NeedleNormalAngle {
                to: [0.0, 1.0, 0.0],
            },
            Cmp::Le,
            1f64.to_radians(),
        );
        assert!(angle.eval(&f));
        let near_jaw = cmp(
            Quantity::NeedleEndDistance {
                end: End::Swage,
                to: Target::RightJaw,
            },
            Cmp::Lt,
            0.003,
        );
        assert!(near_jaw.eval(&f), "2 mm from the jaw");
        assert!(cmp(Quantity::NeedleAge, Cmp::Lt, 1.5).eval(&f), "1 s old");
        let none = Observation::default();
        let f = facts(&none);
        assert!(!cmp(Quantity::NeedleConfidence, Cmp::Lt, 0.8).eval(&f));
        assert!(!cmp(Quantity::NeedleConfidence, Cmp::Ge, 0.8).eval(&f));
        assert!(
            cmp(Quantity::NeedleAge, Cmp::Gt, 1e9).eval(&f),
            "never seen: infinitely old"
        );
        assert!(!Condition::NeedleSeen.eval(&f));
    }

    #[test]
    fn a_needle_point_lies_on_the_estimates_arc_from_tip_to_swage() {
        // The estimate of `seen()`: centre at the origin, normal +y, tip at +x·12 mm; the arc
        // turns about the normal from the tip (+y × +x = −z): through −z·12 mm to the swage.
        let obs = seen();
        let f = facts(&obs);
        let at = |deg: f64| target(&Target::NeedlePoint(deg.to_radians()), &f).expect("seen");
        let near = |a: Point, b: Point| (a - b).norm() < 1e-12;
        assert!(near(at(0.0), Point::new(0.012, 0.0, 0.0)));
        assert!(near(at(90.0), Point::new(0.0, 0.0, -0.012)));
        assert!(near(at(180.0), Point::new(-0.012, 0.0, 0.0)));
        // The handover's grasp site, 20° in from the swage: 4.2 mm of chord from it.
        let site = at(160.0);
        assert!((site.coords.norm() - 0.012).abs() < 1e-12);
        let chord = 2.0 * 0.012 * 10f64.to_radians().sin();
        assert!(((site - Point::new(-0.012, 0.0, 0.0)).norm() - chord).abs() < 1e-12);
        assert!(site.z < 0.0, "on the arc's side, not the other half circle");
        // No estimate, no point: a comparison with it is false.
        let none = Observation::default();
        assert_eq!(target(&Target::NeedlePoint(1.0), &facts(&none)), None);
        let c = cmp(
            Quantity::NeedleEndDistance {
                end: End::Swage,
                to: Target::NeedlePoint(std::f64::consts::PI),
            },
            Cmp::Lt,
            0.001,
        );
        assert!(c.eval(&f) && !c.eval(&facts(&none)));
        assert_eq!(
            c.to_string(),
            "needle_swage_distance(needle_point(deg(180))) < mm(1)"
        );
    }

    /// A thread from (0, -4, 0) cm to (0, 4, 0) cm, or a loop of radius 1 cm round the
    /// origin (`turns` times round, then off radially), each point ±`sigma`.
    fn thread(loop_turns: Option<f64>, sigma: f64) -> Observation {
        let points: Vec<Point> = match loop_turns {
            None => (0..=16)
                .map(|k| Point::new(0.0, -0.04 + 0.005 * f64::from(k), 0.0))
                .collect(),
            Some(turns) => {
                let n = (turns * 36.0).round() as i32;
                (0..=n)
                    .map(|k| {
                        let a = std::f64::consts::TAU * f64::from(k) / 36.0;
                        Point::new(0.01 * a.cos(), 0.01 * a.sin(), 0.002 * f64::from(k) / 36.0)
                    })
                    .chain((1..=8).map(|k| {
                        // Off radially from where the loop ends: no more winding.
                        let a = std::f64::consts::TAU * turns;
                        let r = 0.01 + 0.005 * f64::from(k);
                        Point::new(r * a.cos(), r * a.sin(), 0.003)
                    }))
                    .collect()
            }
        };
        let length_m = points.windows(2).map(|w| (w[1] - w[0]).norm()).sum();
        Observation {
            thread: Some(stitch_primitives::ThreadSeen {
                sigma_m: vec![sigma; points.len()],
                points,
                length_m,
                seen_share: 1.0,
            }),
            left_jaw: Some(Point::new(0.02, 0.0, 0.0)),
            right_jaw: Some(Point::origin()),
            ..seen()
        }
    }

    #[test]
    fn thread_quantities_read_the_trace_and_are_false_without_one() {
        let left = Target::LeftJaw;
        let clear = |b: f64| cmp(Quantity::ThreadClearance { from: left }, Cmp::Gt, b);
        // The straight thread passes 2 cm from the left jaw: 2 cm less 2σ.
        let obs = thread(None, 0.001);
        let f = facts(&obs);
        assert!(clear(0.017).eval(&f) && !clear(0.019).eval(&f));
        // Less sure, less clear.
        let unsure = thread(None, 0.004);
        assert!(!clear(0.013).eval(&facts(&unsure)) && clear(0.011).eval(&facts(&unsure)));
        assert!(cmp(Quantity::ThreadFree, Cmp::Gt, 0.079).eval(&f));
        assert!(!cmp(Quantity::ThreadFree, Cmp::Gt, 0.081).eval(&f));
        // A straight thread past the origin turns half round it; a loop once and a quarter
        // round it, 450°.
        let wrap = |q: f64, o: &Observation| {
            cmp(
                Quantity::ThreadWrap {
                    round: Target::RightJaw,
                },
                Cmp::Ge,
                q.to_radians(),
            )
            .eval(&facts(o))
        };
        assert!(wrap(170.0, &obs) && !wrap(190.0, &obs));
        let looped = thread(Some(1.25), 0.001);
        assert!(wrap(440.0, &looped) && !wrap(460.0, &looped));
        // A thread more than 3 cm off does not wind round the point at all.
        let far = cmp(
            Quantity::ThreadWrap {
                round: Target::Point([0.2, 0.0, 0.0]),
            },
            Cmp::Gt,
            0.0,
        );
        assert!(!far.eval(&facts(&looped)));
        // No trace, no value: every comparison false.
        let none = seen();
        for q in [
            Quantity::ThreadFree,
            Quantity::ThreadClearance { from: left },
            Quantity::ThreadWrap { round: left },
        ] {
            assert!(q.needs_thread() && q.needs_needle());
            assert!(!cmp(q, Cmp::Ge, -1e9).eval(&facts(&none)), "{q:?}");
            assert!(!cmp(q, Cmp::Lt, 1e9).eval(&facts(&none)), "{q:?}");
        }
        assert_eq!(
            clear(0.005).to_string(),
            "thread_clearance(left_jaw()) > mm(5)"
        );
    }

    #[test]
    fn the_engine_settles_mission_conditions_and_leaves_the_rest_open() {
        let m = facts(&Observation::default()).mission;
        let throw2 = cmp(Quantity::ThrowNumber, Cmp::Eq, 2.0);
        assert_eq!(throw2.eval_known(&m), Some(true));
        let unsure = cmp(Quantity::NeedleConfidence, Cmp::Lt, 0.8);
        let both = Condition::All {
            of: vec![throw2.clone(), unsure.clone()],
        };
        assert_eq!(both.eval_known(&m), None);
        let either = Condition::Any {
            of: vec![unsure.clone(), throw2.clone()],
        };
        assert_eq!(either.eval_known(&m), Some(true));
        let not_first = Condition::Not {
            of: Box::new(cmp(Quantity::ThrowNumber, Cmp::Eq, 1.0)),
        };
        assert_eq!(not_first.eval_known(&m), Some(true));
        // No thread length given: no value, so no comparison holds.
        assert_eq!(
            cmp(Quantity::ThreadLeft, Cmp::Lt, 1.0).eval_known(&m),
            Some(false)
        );
    }

    #[test]
    fn conditions_print_as_scripts_write_them() {
        let c = Condition::All {
            of: vec![
                cmp(Quantity::NeedleConfidence, Cmp::Ge, 0.8),
                Condition::Not {
                    of: Box::new(cmp(Quantity::NeedleAge, Cmp::Gt, 2.0)),
                },
                cmp(Quantity::ThreadLeft, Cmp::Lt, 0.05),
            ],
        };
        assert_eq!(
            c.to_string(),
            "all([needle_confidence() >= 0.8, not(needle_age() > s(2)), thread_left() < mm(50)])"
        );
    }
}
