//! Hostile files: a recording with bytes flipped, cut, or replaced is read (or recovered) to a
//! typed error or to what survives, never a panic or a hang.

use proptest::prelude::*;
use std::path::PathBuf;
use stitch_engine::{Entry, Journal};
use stitch_recorder::{Recorder, RecorderOptions, RunInfo};

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("stitch-recorder-test-{}", std::process::id()));
    std::fs::create_dir_all(&d).expect("temp dir");
    d.join(name)
}

/// A small real recording: a plan record, transitions and step events.
fn recording() -> Vec<u8> {
    let path = tmp("source.mcap");
    let info = RunInfo {
        program: "stitch test".into(),
        plan_file: "p.rhai".into(),
        plan_text: "mission(\"m\", []);".into(),
        seed: Some(1),
        robot: "scripted".into(),
        ..RunInfo::default()
    };
    let recorder = Recorder::create(&path, &info, RecorderOptions::default()).expect("created");
    let mut journal = Journal::new();
    journal.stream_to(recorder.sink());
    journal.push(Entry::Plan {
        name: "m".into(),
        file: "p.rhai".into(),
        throws: 1,
        interventions: 0,
        seed: Some(1),
        params: Default::default(),
    });
    for i in 0..20u64 {
        journal.set_now(std::time::Duration::from_millis(300 * i));
        journal.push(Entry::Transition {
            from: format!("s{i}"),
            to: format!("s{}", i + 1),
        });
    }
    journal.stop_streaming();
    recorder.finish().expect("finished");
    std::fs::read(&path).expect("read back")
}

fn source() -> &'static [u8] {
    static BYTES: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
    BYTES.get_or_init(recording)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: std::env::var("STITCH_PROPTEST_CASES").ok().and_then(|c| c.parse().ok()).unwrap_or(500), ..ProptestConfig::default() })]

    #[test]
    fn flipped_cut_or_spliced_bytes_never_panic(
        flips in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..12),
        cut in any::<prop::sample::Index>(),
        junk in prop::collection::vec(any::<u8>(), 0..64),
    ) {
        let mut bytes = source().to_vec();
        for (at, value) in &flips {
            let i = at.index(bytes.len());
            bytes[i] = *value;
        }
        bytes.truncate(cut.index(bytes.len() + 1));
        bytes.extend_from_slice(&junk);
        let path = tmp(&format!("hostile-{}.mcap", std::thread::current().name().unwrap_or("t").replace("::", "-")));
        std::fs::write(&path, &bytes).expect("written");
        // Either a typed error naming the file, or what could be read; never a panic.
        match stitch_recorder::read(&path) {
            Ok(got) => prop_assert!(got.records.len() <= 21),
            Err(e) => prop_assert!(e.to_string().contains("hostile-"), "{e}"),
        }
        let out = path.with_extension("out.mcap");
        let _ = stitch_recorder::recover(&path, &out);
    }
}

#[test]
fn the_source_recording_reads_whole() {
    let path = tmp("whole.mcap");
    std::fs::write(&path, source()).expect("written");
    let got = stitch_recorder::read(&path).expect("reads");
    assert!(got.complete);
    assert_eq!(got.records.len(), 21);
}

#[test]
fn a_chunk_holding_a_chunk_that_overruns_it_is_refused_not_a_panic() {
    // Found by the `recording` fuzz target (fuzz/README.md), minimised: the mcap crate's
    // reader panicked (subtract with overflow) on a record inside a chunk, itself a chunk,
    // claiming more bytes than were left.
    let bytes = include_bytes!("data/fuzz-chunk-record-overrun.mcap");
    let path = std::path::Path::new("fuzz-chunk-record-overrun.mcap");
    let e = stitch_recorder::read_bytes(path, bytes).expect_err("refused");
    let text = e.to_string();
    assert!(text.contains("inside a chunk"), "{text}");
    assert!(text.contains("fuzz-chunk-record-overrun.mcap"), "{text}");
}

#[test]
fn an_attachment_shorter_than_its_own_header_is_refused_not_a_panic() {
    // Found by the `recording` fuzz target, minimised: the mcap crate's reader panicked
    // (slice index out of range) on it; the recorder catches that and says what it is.
    let bytes = include_bytes!("data/fuzz-attachment-shorter-than-header.mcap");
    let path = std::path::Path::new("fuzz-attachment.mcap");
    let e = stitch_recorder::read_bytes(path, bytes).expect_err("refused");
    let text = e.to_string();
    assert!(text.contains("a malformed record"), "{text}");
    assert!(text.contains("fuzz-attachment.mcap"), "{text}");
}

/// Where the top-level records with `opcode` start (by their framing), after the magic.
fn records_with_opcode(bytes: &[u8], opcode: u8) -> Vec<(usize, usize)> {
    let (mut at, mut found) = (8, Vec::new());
    while at + 9 <= bytes.len() {
        let len = u64::from_le_bytes(bytes[at + 1..at + 9].try_into().expect("8 bytes")) as usize;
        if bytes[at] == opcode {
            found.push((at, at + 9 + len));
        }
        at += 9 + len;
    }
    found
}

#[test]
fn a_damaged_record_inside_a_finished_file_is_an_error_naming_where_not_a_cut_short_tail() {
    // Before, any record the reader could not read ended the reading, as a file cut short by
    // a crash does: a bit flipped in the middle of a finished file gave the records before it
    // and said nothing of the rest.
    let mut bytes = source().to_vec();
    let chunks = records_with_opcode(&bytes, 0x06);
    let (start, end) = chunks[1];
    assert!(
        end < bytes.len() - 100,
        "the chunk is followed by more of the file"
    );
    bytes[end - 3] ^= 0x40; // inside the chunk's records: its checksum no longer matches
    let path = tmp("damaged.mcap");
    std::fs::write(&path, &bytes).expect("written");
    let e = stitch_recorder::read(&path).expect_err("a damaged file is refused");
    let text = e.to_string();
    assert!(
        text.contains(&format!("at byte {start}"))
            && text.contains("damaged")
            && text.contains("damaged.mcap"),
        "{text}"
    );
    // A record's framing broken in the middle of the file (its opcode turned into a
    // chunk's, whose header it cannot hold) is damage too, not a tail cut short.
    let mut bytes = source().to_vec();
    let (at, _) = records_with_opcode(&bytes, 0x07)[0];
    bytes[at] = 0x06;
    std::fs::write(&path, &bytes).expect("written");
    let e = stitch_recorder::read(&path).expect_err("a damaged file is refused");
    let text = e.to_string();
    assert!(
        text.contains(&format!("at byte {at}")) && text.contains("damaged"),
        "{text}"
    );
}

#[test]
fn a_file_cut_short_or_ending_in_zeros_a_crash_left_is_read_to_its_last_whole_record() {
    let bytes = source();
    let (_, end) = records_with_opcode(bytes, 0x06)[1];
    for (name, tail) in [("cut.mcap", vec![0xAB; 5]), ("zeros.mcap", vec![0; 4096])] {
        // The first chunk whole, then a record cut short (or zeros).
        let mut cut = bytes[..end].to_vec();
        cut.extend_from_slice(&tail);
        let path = tmp(name);
        std::fs::write(&path, &cut).expect("written");
        let got = stitch_recorder::read(&path).expect("an unfinished file is read");
        assert!(!got.complete, "{name}");
        assert!(!got.records.is_empty(), "{name}: the first chunk's records");
    }
}
