//! A flight recording (`stitch journal show|export|recover FILE.mcap`), any bytes: read up
//! to what stands, or refused with a clear error, never a panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    // The recorder catches panics of the `mcap` crate's reader and turns them into errors
    // (recorder/src/read.rs); libFuzzer's hook would abort on them before they are caught.
    // Back to the default hook (taking the installed one registers the default): a panic
    // that escapes still aborts (libfuzzer-sys does so when one reaches it) and is a crash.
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| drop(std::panic::take_hook()));
    if let Ok(r) = stitch_recorder::read_bytes(Path::new("fuzz.mcap"), data) {
        let _ = stitch_recorder::to_jsonl(&r.records);
    }
});
