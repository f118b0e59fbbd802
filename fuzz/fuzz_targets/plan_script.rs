//! A plan script, any text: evaluated in the sandbox (default limits) and validated. It must
//! end in a plan or a clear error, within the sandbox's deadline, never a panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use std::sync::OnceLock;
use stitch_engine::{PlanLoader, ScriptLimits, load_plan_str};
use stitch_robot::{Wound, WoundSpec};

fn loader() -> &'static PlanLoader {
    static LOADER: OnceLock<PlanLoader> = OnceLock::new();
    LOADER.get_or_init(|| {
        let wound = Wound::linear(&WoundSpec::default()).expect("the default wound");
        PlanLoader::new(&wound, ScriptLimits::default())
    })
}

fuzz_target!(|data: &[u8]| {
    let Ok(source) = std::str::from_utf8(data) else {
        return;
    };
    if let Err(errors) = load_plan_str(loader(), "fuzz.rhai", source) {
        // Every error names its place and says something.
        let text = errors.to_string();
        assert!(text.contains("fuzz.rhai"), "{text}");
    }
});
