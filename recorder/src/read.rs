//! Reading a recorded run back: whole, or up to the last chunk an interrupted writer closed;
//! [`recover`] writes a complete file from an unfinished one.

use crate::RecorderError;
use crate::msgs::Event;
use mcap::read::{LinearReader, Options};
use mcap::records::{self, Record as McapRecord};
use std::borrow::Cow;
use std::collections::BTreeMap;
use std::path::Path;
use stitch_engine::Record;

/// What a recording holds.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Recorded {
    /// The file's profile and writing library.
    pub header: (String, String),
    /// The run's metadata (`stitch_run`: program, plan file and hash, seed, robot).
    pub metadata: Vec<(String, BTreeMap<String, String>)>,
    /// Attachments: name, media type, bytes (the plan script, the mock configuration).
    pub attachments: Vec<(String, String, Vec<u8>)>,
    /// Schemas by id: name, encoding, text.
    pub schemas: BTreeMap<u16, (String, String, Vec<u8>)>,
    /// Channels by id.
    pub channels: BTreeMap<u16, records::Channel>,
    /// Every message in file order: channel, log time (ns), bytes.
    pub messages: Vec<(u16, u64, Vec<u8>)>,
    /// The engine's journal, from `/stitch/events`.
    pub records: Vec<Record>,
    /// Whether the file was finished (summary and footer written); an unfinished one was read
    /// up to its last closed chunk.
    pub complete: bool,
}

fn bad(path: &Path, why: impl std::fmt::Display) -> RecorderError {
    RecorderError::Mcap {
        path: path.display().to_string(),
        why: why.to_string(),
    }
}

/// Read `path`, finished or not (an interrupted run's file is read up to its last closed
/// chunk; what follows it is not a record and is left).
pub fn read(path: &Path) -> Result<Recorded, RecorderError> {
    let buf = std::fs::read(path).map_err(|error| RecorderError::Io {
        path: path.display().to_string(),
        error,
    })?;
    read_bytes(path, &buf)
}

/// [`read`] of a file's bytes, `path` naming it in errors.
pub fn read_bytes(path: &Path, buf: &[u8]) -> Result<Recorded, RecorderError> {
    // The `mcap` crate's reader (0.26) panics on some malformed records instead of saying
    // so (a slice out of bounds in an attachment shorter than its own header, a subtraction
    // that overflows in a nested chunk: both found by the `recording` fuzz target, both
    // regression tests in tests/hostile.rs). A file a crash or a disk mangled must get a
    // clear error, never take the program down: a panic inside the reader is caught and said.
    // Written by hand because no other maintained Rust MCAP reader exists.
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| parse(path, buf))).unwrap_or_else(
        |panic| {
            let what = panic
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| panic.downcast_ref::<&str>().map(|s| (*s).to_string()))
                .unwrap_or_default();
            Err(bad(
                path,
                format!("a malformed record (the MCAP reader failed on it: {what})"),
            ))
        },
    )
}

fn parse(path: &Path, buf: &[u8]) -> Result<Recorded, RecorderError> {
    let complete = LinearReader::new(buf)
        .map(|r| r.into_iter().all(|x| x.is_ok()))
        .unwrap_or(false);
    let mut out = Recorded {
        complete,
        ..Recorded::default()
    };
    let reader = LinearReader::new_with_options(buf, Options::IgnoreEndMagic.into())
        .map_err(|e| bad(path, format!("not an MCAP file: {e}")))?;
    let frames = frames(buf);
    for (n, record) in reader.enumerate() {
        match record {
            Ok(record) => take(path, &mut out, record).map_err(|e| match e {
                RecorderError::Mcap { path, why } => RecorderError::Mcap {
                    path,
                    why: format!(
                        "record {n} at byte {}: {why}",
                        frames.whole.get(n).copied().unwrap_or(0)
                    ),
                },
                other => other,
            })?,
            Err(e) => match frames.whole.get(n) {
                // A record whose bytes are all there, yet unreadable: the file is damaged
                // (a flipped bit, a bad checksum), not cut short. What follows it would be
                // lost without a word, so it is an error, and says where.
                Some(&at) if !buf[at..].iter().all(|&b| b == 0) => {
                    return Err(bad(
                        path,
                        format!(
                            "record {n} at byte {at} is damaged, with {} bytes after it: {e}",
                            buf.len() - frames.end_of(n)
                        ),
                    ));
                }
                // An unfinished file ends in a record cut short (or in zeros a crash left):
                // everything before it stands.
                _ => break,
            },
        }
    }
    if out.header.0.is_empty() {
        return Err(bad(path, "no MCAP header"));
    }
    let events = out
        .channels
        .values()
        .find(|c| c.topic == "/stitch/events")
        .map(|c| c.id);
    for (channel, _, bytes) in &out.messages {
        if Some(*channel) != events {
            continue;
        }
        let event: Event = stitch_dvrk::decode(bytes, "stitch_msgs/msg/Event").map_err(|e| {
            RecorderError::Message {
                path: path.display().to_string(),
                why: e.to_string(),
            }
        })?;
        let record: Record =
            serde_json::from_str(&event.record_json).map_err(|e| RecorderError::Message {
                path: path.display().to_string(),
                why: format!("event {}: {e}", event.seq),
            })?;
        out.records.push(record);
    }
    Ok(out)
}

fn take(path: &Path, out: &mut Recorded, record: McapRecord<'_>) -> Result<(), RecorderError> {
    match record {
        McapRecord::Header(h) => out.header = (h.profile, h.library),
        McapRecord::Metadata(m) => out.metadata.push((m.name, m.metadata)),
        McapRecord::Attachment { header, data, .. } => {
            out.attachments
                .push((header.name, header.media_type, data.into_owned()));
        }
        McapRecord::Schema { header, data } => {
            out.schemas
                .insert(header.id, (header.name, header.encoding, data.into_owned()));
        }
        McapRecord::Channel(c) => {
            out.channels.insert(c.id, c);
        }
        McapRecord::Message { header, data } => {
            out.messages
                .push((header.channel_id, header.log_time, data.into_owned()));
        }
        McapRecord::Chunk { header, data } => {
            if !header.compression.is_empty() {
                return Err(bad(
                    path,
                    format!(
                        "a {} chunk: this build reads uncompressed chunks",
                        header.compression
                    ),
                ));
            }
            chunk_records_fit(&data).map_err(|why| bad(path, format!("inside a chunk: {why}")))?;
            // The reader does not check a chunk's checksum: a flipped bit in a record's
            // payload would be read as if it were what was written.
            if header.uncompressed_crc != 0 && crc32fast::hash(&data) != header.uncompressed_crc {
                return Err(bad(
                    path,
                    "a chunk is damaged: its checksum does not match its records",
                ));
            }
            for inner in LinearReader::sans_magic(&data) {
                let inner = inner.map_err(|e| bad(path, format!("inside a chunk: {e}")))?;
                take(path, out, inner)?;
            }
        }
        _ => {}
    }
    Ok(())
}

/// Where a file's top-level records lie, by their framing alone (opcode, length): the start
/// of each one whose bytes are all in the file, up to the footer. A record that claims more
/// bytes than are left is a tail cut short and is not listed.
struct Frames {
    whole: Vec<usize>,
    ends: Vec<usize>,
}

impl Frames {
    /// Where record `n` ends (the file's end when it is not whole).
    fn end_of(&self, n: usize) -> usize {
        self.ends.get(n).copied().unwrap_or(usize::MAX)
    }
}

fn frames(buf: &[u8]) -> Frames {
    const MAGIC_LEN: usize = 8;
    const FOOTER: u8 = 0x02;
    let (mut whole, mut ends) = (Vec::new(), Vec::new());
    let mut at = MAGIC_LEN;
    while let Some(head) = buf.get(at..at + 9) {
        let mut len = [0u8; 8];
        len.copy_from_slice(&head[1..]);
        let Some(end) = usize::try_from(u64::from_le_bytes(len))
            .ok()
            .and_then(|l| (at + 9).checked_add(l))
            .filter(|&end| end <= buf.len())
        else {
            break;
        };
        whole.push(at);
        ends.push(end);
        if head[0] == FOOTER {
            break;
        }
        at = end;
    }
    Frames { whole, ends }
}

/// Whether a chunk's records lie within it, none of them a chunk: checked before the `mcap`
/// crate reads them, because its reader (0.26) subtracts a record's length from what is left
/// of a chunk without checking, and panics on a record inside a chunk (which MCAP does not
/// allow) that claims more bytes than the chunk has (found by the `recording` fuzz target).
fn chunk_records_fit(data: &[u8]) -> Result<(), String> {
    const CHUNK: u8 = 0x06;
    let mut at = 0usize;
    while at < data.len() {
        let Some(head) = data.get(at..at + 9) else {
            return Err(format!("a record header cut short at byte {at}"));
        };
        let opcode = head[0];
        let mut len = [0u8; 8];
        len.copy_from_slice(&head[1..]);
        let len = u64::from_le_bytes(len);
        if opcode == CHUNK {
            return Err(format!("a chunk at byte {at}: chunks do not nest"));
        }
        let end = usize::try_from(len)
            .ok()
            .and_then(|l| (at + 9).checked_add(l))
            .filter(|&end| end <= data.len())
            .ok_or_else(|| {
                format!(
                    "a record of {len} bytes at byte {at} runs past the chunk's end ({} bytes)",
                    data.len()
                )
            })?;
        at = end;
    }
    Ok(())
}

/// Write to `to` a complete file holding everything `from` holds up to its last closed chunk:
/// metadata, attachments, schemas, channels and messages, in order.
pub fn recover(from: &Path, to: &Path) -> Result<Recorded, RecorderError> {
    rewrite(from, to, |_, _, _| {})
}

/// [`recover`], letting `edit` change each message on the way: it gets the topic, the
/// message's index on it (from 0) and its bytes. For tools and tests (a recording with one
/// value altered, to see `stitch replay` find it).
pub fn rewrite(
    from: &Path,
    to: &Path,
    mut edit: impl FnMut(&str, u32, &mut Vec<u8>),
) -> Result<Recorded, RecorderError> {
    let got = read(from)?;
    let file = std::fs::File::create(to).map_err(|error| RecorderError::Io {
        path: to.display().to_string(),
        error,
    })?;
    let err = |e: mcap::McapError| bad(to, e);
    let mut w = mcap::WriteOptions::new()
        .profile(got.header.0.clone())
        .library(got.header.1.clone())
        .compression(None)
        .chunk_size(None)
        .create(std::io::BufWriter::new(file))
        .map_err(err)?;
    for (name, metadata) in &got.metadata {
        w.write_metadata(&records::Metadata {
            name: name.clone(),
            metadata: metadata.clone(),
        })
        .map_err(err)?;
    }
    for (name, media_type, data) in &got.attachments {
        w.attach(&mcap::Attachment {
            log_time: 0,
            create_time: 0,
            name: name.clone(),
            media_type: media_type.clone(),
            data: Cow::Borrowed(data),
        })
        .map_err(err)?;
    }
    // Schemas and channels in the order their first messages come, each just before it:
    // never a chunk of them alone, which Foxglove's indexed reader refuses (a channel with no
    // message is left out).
    let mut schema_ids: BTreeMap<u16, u16> = BTreeMap::new();
    let mut channel_ids: BTreeMap<u16, u16> = BTreeMap::new();
    let mut sequence: BTreeMap<u16, u32> = BTreeMap::new();
    for (channel, t, data) in &got.messages {
        if !channel_ids.contains_key(channel) {
            let Some(c) = got.channels.get(channel) else {
                return Err(bad(from, format!("a message on unknown channel {channel}")));
            };
            let schema = match (schema_ids.get(&c.schema_id), got.schemas.get(&c.schema_id)) {
                (Some(s), _) => *s,
                (None, Some((name, encoding, data))) => {
                    let s = w.add_schema(name, encoding, data).map_err(err)?;
                    schema_ids.insert(c.schema_id, s);
                    s
                }
                (None, None) => 0,
            };
            let id = w
                .add_channel(schema, &c.topic, &c.message_encoding, &c.metadata)
                .map_err(err)?;
            channel_ids.insert(*channel, id);
        }
        let Some(id) = channel_ids.get(channel) else {
            return Err(bad(from, format!("a message on unknown channel {channel}")));
        };
        let seq = sequence.entry(*id).or_default();
        let mut data = data.clone();
        if let Some(c) = got.channels.get(channel) {
            edit(&c.topic, *seq, &mut data);
        }
        w.write_to_known_channel(
            &records::MessageHeader {
                channel_id: *id,
                sequence: *seq,
                log_time: *t,
                publish_time: *t,
            },
            &data,
        )
        .map_err(err)?;
        *seq += 1;
    }
    w.finish().map_err(err)?;
    Ok(got)
}

/// Records as JSON Lines, as the journal writes them.
pub fn to_jsonl(records: &[Record]) -> String {
    let mut out = String::new();
    for r in records {
        if let Ok(line) = serde_json::to_string(r) {
            out.push_str(&line);
            out.push('\n');
        }
    }
    out
}
