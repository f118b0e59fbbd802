//! A flight recording (`stitch journal show|export|recover FILE.mcap`), any bytes: read up
//! to what stands, or refused with a clear error, never a panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    if let Ok(r) = stitch_recorder::read_bytes(Path::new("fuzz.mcap"), data) {
        let _ = stitch_recorder::to_jsonl(&r.records);
    }
});
