//! The scripting reference, generated from what the sandbox registers: every function a plan
//! may call ([`crate::API`]) and every primitive's parameters with their units, defaults and
//! ranges (`stitch_primitives::param_specs`). `docs/scripting.md` holds it between two marker
//! lines; a test fails when the file is stale.

use crate::plan::caps;
use std::fmt::Write as _;
use stitch_primitives::{Quantity, STEP_NAMES, StepKind, Value};

/// The line before the generated reference in `docs/scripting.md`.
pub const REFERENCE_BEGIN: &str = "<!-- BEGIN GENERATED REFERENCE -->";
/// The line after it.
pub const REFERENCE_END: &str = "<!-- END GENERATED REFERENCE -->";

fn shown(q: Quantity, v: f64) -> String {
    let trim = |x: f64| {
        let s = format!("{x:.2}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    };
    match q {
        Quantity::Length => format!("{} mm", trim(v * 1e3)),
        Quantity::Angle => format!("{}°", trim(v.to_degrees())),
        Quantity::Count => format!("{}", v.round() as i64),
    }
}

/// The reference, as Markdown (without the marker lines).
pub fn reference_markdown() -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "Generated from the sandbox's registered functions and the primitives' parameter \
         tables (`cargo test -p stitch-engine --test script` checks it; \
         `STITCH_UPDATE_DOCS=1` rewrites it).\n"
    );
    let _ = writeln!(s, "| function | use |");
    let _ = writeln!(s, "|---|---|");
    for (name, usage) in crate::API {
        let _ = writeln!(s, "| `{name}` | {} |", usage.replace('|', "\\|"));
    }
    let _ = writeln!(
        s,
        "\nEngine caps: retries {} (extract), {} (handover), {} (perception); interventions \
         {}; throws {}; `repeat` max {}; constructs nested {} deep; {} steps on a throw's \
         longest path; {} operations in a throw's program (loops unrolled); {} terms in a \
         condition.\n",
        caps::EXTRACT_RETRIES,
        caps::HANDOVER_RETRIES,
        caps::PERCEPTION_RETRIES,
        caps::INTERVENTIONS,
        caps::THROWS,
        caps::REPEAT,
        caps::NESTING,
        caps::STEPS_PER_THROW,
        caps::OPS_PER_THROW,
        caps::CONDITION_TERMS
    );
    for name in STEP_NAMES {
        let Some(kind) = StepKind::default_for(name) else {
            continue;
        };
        let specs = kind.param_specs();
        let _ = writeln!(s, "#### `{name}` parameters\n");
        if specs.is_empty() {
            let _ = writeln!(s, "None.\n");
            continue;
        }
        let _ = writeln!(s, "| parameter | unit | default | range | meaning |");
        let _ = writeln!(s, "|---|---|---|---|---|");
        for spec in specs {
            let unit = match spec.quantity {
                Quantity::Length => "length",
                Quantity::Angle => "angle",
                Quantity::Count => "count",
            };
            let default = match kind.get(spec.name) {
                Some(Value::Length(v) | Value::Angle(v)) => shown(spec.quantity, v),
                Some(Value::Count(n)) => n.to_string(),
                None => "—".into(),
            };
            let _ = writeln!(
                s,
                "| `{}` | {unit} | {default} | {} to {} | {} |",
                spec.name,
                shown(spec.quantity, spec.range.min),
                shown(spec.quantity, spec.range.max),
                spec.doc.replace('|', "\\|")
            );
        }
        let _ = writeln!(s);
    }
    s
}
