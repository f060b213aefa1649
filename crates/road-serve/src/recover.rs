//! Recordings cut off by a killed server, rewritten whole. A server killed mid-scene leaves its
//! recordings without their summary and footer, often ending inside a record (the chunk it was
//! filling); stream readers read such a file up to the cut, but the default readers of the
//! MCAP libraries (Python's `make_reader`, the `mcap` CLI) read the summary first and fail.
//! [`recover`] reads every complete record before the cut and writes the file again, whole:
//! schemas, channels and messages in their order, then the summary, footer and end magic.
//!
//! `road recover FILE…` runs it; a server runs [`recover_folder`] on its recording folder at
//! start, for the files a killed predecessor left there.

use std::collections::BTreeSet;
use std::fs::File;
use std::io::{BufWriter, Read};
use std::path::{Path, PathBuf};

use mcap::McapResult;
use mcap::records::{Record, op};

use crate::record::{is_recording_name, try_lock_exclusive};
use crate::{Error, Result};

/// The footer record, opcode and length included.
const FOOTER_RECORD_LEN: usize = 1 + 8 + 20;

/// What [`recover`] did with a file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Recovery {
    /// The file ends with its summary, footer and end magic: left untouched.
    Complete,
    /// The file was cut off and has been rewritten whole.
    Recovered(Recovered),
}

/// What a cut-off file held.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Recovered {
    /// Messages kept: every message of the complete records before the cut (a chunk counts
    /// only whole).
    pub messages: u64,
    /// The cut-off file's bytes up to the end of its last complete record.
    pub kept_bytes: u64,
    /// The bytes after it: the partial record (or chunk) at the cut, or a partial summary.
    pub dropped_bytes: u64,
}

/// Whether the file at `path` ends as a finished MCAP file does: a footer record and the end
/// magic after it. Reads only its first and last bytes.
pub fn has_footer(path: &Path) -> Result<bool> {
    use std::io::{Seek, SeekFrom};
    let io_err = |source| Error::Io {
        path: path.to_owned(),
        source,
    };
    let mut file = File::open(path).map_err(io_err)?;
    let len = file.metadata().map_err(io_err)?.len();
    let tail_len = FOOTER_RECORD_LEN + mcap::MAGIC.len();
    if len < (mcap::MAGIC.len() + tail_len) as u64 {
        return Ok(false);
    }
    let mut start = [0u8; 8];
    file.read_exact(&mut start).map_err(io_err)?;
    let mut tail = vec![0u8; tail_len];
    file.seek(SeekFrom::End(-(tail_len as i64)))
        .map_err(io_err)?;
    file.read_exact(&mut tail).map_err(io_err)?;
    Ok(start == *mcap::MAGIC && ends_with_footer(&tail))
}

/// `bytes` end with a footer record and the end magic.
fn ends_with_footer(bytes: &[u8]) -> bool {
    let tail_len = FOOTER_RECORD_LEN + mcap::MAGIC.len();
    if bytes.len() < tail_len || !bytes.ends_with(mcap::MAGIC) {
        return false;
    }
    let footer = &bytes[bytes.len() - tail_len..];
    footer[0] == op::FOOTER && footer[1..9] == (20u64).to_le_bytes()
}

/// Where [`recover`] writes the new file before it replaces the old: `FILE.recovering`.
pub fn recovering_path(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_owned();
    name.push(".recovering");
    path.with_file_name(name)
}

/// Rewrites the recording at `path` whole if it was cut off (no footer): every complete
/// record before the cut is kept, in order, and the summary, footer and end magic follow.
/// The new file is written next to it (`FILE.recovering`), synced, and renamed over it: on
/// any failure the file is left as it was and nothing else remains.
///
/// A file that ends with its footer is left untouched ([`Recovery::Complete`]). A file that
/// does not start with the MCAP magic is an [`Error::Recover`]; one whose lock a running
/// server holds (it is writing it) is [`Error::RecordingInUse`].
pub fn recover(path: &Path) -> Result<Recovery> {
    let io_err = |source| Error::Io {
        path: path.to_owned(),
        source,
    };
    let fail = |reason: String| Error::Recover {
        path: path.to_owned(),
        reason,
    };
    let mut file = File::open(path).map_err(io_err)?;
    // Held until the new file has replaced this one.
    if !try_lock_exclusive(&file).map_err(io_err)? {
        return Err(Error::RecordingInUse {
            path: path.to_owned(),
        });
    }
    let mut bytes = Vec::new();
    file.read_to_end(&mut bytes).map_err(io_err)?;
    if !bytes.starts_with(mcap::MAGIC) {
        return Err(fail(
            if bytes.len() < mcap::MAGIC.len() && mcap::MAGIC.starts_with(&bytes) {
                format!(
                    "it was cut off before its first record ({} bytes): nothing to recover",
                    bytes.len()
                )
            } else {
                "not an MCAP file (it does not start with the MCAP magic)".to_owned()
            },
        ));
    }
    if ends_with_footer(&bytes) {
        return match mcap::Summary::read(&bytes) {
            Ok(_) => Ok(Recovery::Complete),
            Err(e) => Err(fail(format!(
                "it ends with a footer (it was not cut off) but its summary does not read ({e}); \
                 left as is"
            ))),
        };
    }
    let tmp = recovering_path(path);
    let result = rewrite(&bytes, &tmp).and_then(|recovered| {
        std::fs::rename(&tmp, path)
            .map_err(|e| format!("cannot rename {} over it: {e}", tmp.display()))?;
        // The rename itself survives a crash once the folder is synced (not every file
        // system can sync a folder: the file is whole either way).
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            let _ = File::open(dir).and_then(|d| d.sync_all());
        }
        Ok(recovered)
    });
    drop(file);
    match result {
        Ok(recovered) => Ok(Recovery::Recovered(recovered)),
        Err(reason) => {
            let _ = std::fs::remove_file(&tmp);
            Err(fail(reason))
        }
    }
}

/// Recovers every cut-off recording in `dir` (the files named as [`crate::record::free_path`]
/// names them and without a footer): what a server does at start, before its first scene,
/// for the files a killed predecessor left. Each file recovered is logged (a warning: a
/// server was killed), and so is each failure; neither stops the caller. A missing folder
/// holds nothing. Returns every file tried and what came of it.
pub fn recover_folder(dir: &Path) -> Vec<(PathBuf, Result<Recovery>)> {
    let entries = match std::fs::read_dir(dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Vec::new(),
        Err(e) => {
            tracing::warn!(folder = %dir.display(), "cannot list the recordings to recover: {e}");
            return Vec::new();
        }
    };
    let mut paths: Vec<PathBuf> = entries
        .filter_map(|entry| entry.ok())
        .filter(|entry| entry.file_type().is_ok_and(|t| t.is_file()))
        .filter(|entry| entry.file_name().to_str().is_some_and(is_recording_name))
        .map(|entry| entry.path())
        .collect();
    paths.sort();
    let mut outcomes = Vec::new();
    for path in paths {
        let outcome = match has_footer(&path) {
            Ok(true) => continue,
            Ok(false) => recover(&path),
            Err(e) => Err(e),
        };
        match &outcome {
            Ok(Recovery::Recovered(r)) => tracing::warn!(
                file = %path.display(),
                messages = r.messages,
                dropped_bytes = r.dropped_bytes,
                "recovered a recording cut off by a killed server: {} messages kept, {} trailing \
                 bytes dropped",
                r.messages,
                r.dropped_bytes
            ),
            Ok(Recovery::Complete) => {}
            Err(Error::RecordingInUse { .. }) => tracing::info!(
                file = %path.display(),
                "a recording without its summary is being written by another running server; \
                 left alone"
            ),
            Err(e) => tracing::warn!(
                file = %path.display(),
                "cannot recover a cut-off recording: {}",
                error_chain(e)
            ),
        }
        outcomes.push((path, outcome));
    }
    outcomes
}

/// An error with its sources, for a log line.
fn error_chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        text.push_str(": ");
        text.push_str(&s.to_string());
        source = s.source();
    }
    text
}

/// The records of a cut-off file, from the start, one unit at a time: a record, or a chunk's
/// records (a chunk is used whole or not at all: its CRC is checked). The walk stops at the
/// first record that is cut off or does not parse, or after the data end record.
struct Walk<'a> {
    bytes: &'a [u8],
    /// Where the next record starts: after the last complete one.
    pos: usize,
    done: bool,
}

impl<'a> Walk<'a> {
    fn new(bytes: &'a [u8]) -> Self {
        Self {
            bytes,
            pos: mcap::MAGIC.len(),
            done: false,
        }
    }
}

impl Iterator for Walk<'_> {
    type Item = Vec<Record<'static>>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        let unit = (|| {
            let rest = &self.bytes[self.pos..];
            let (&opcode, rest) = rest.split_first()?;
            let len = u64::from_le_bytes(rest.get(..8)?.try_into().ok()?);
            let len = usize::try_from(len).ok()?;
            let body = rest.get(8..8usize.checked_add(len)?)?;
            let records = match mcap::parse_record(opcode, body).ok()? {
                Record::Chunk { header, data } => mcap::read::ChunkReader::new(header, &data)
                    .ok()?
                    .map(|r| r.map(Record::into_owned))
                    .collect::<McapResult<Vec<_>>>()
                    .ok()?,
                record => vec![record.into_owned()],
            };
            Some((records, 1 + 8 + len))
        })();
        match unit {
            Some((records, len)) => {
                self.pos += len;
                // The data section ends here; the summary after it is written anew.
                self.done = records
                    .iter()
                    .any(|r| matches!(r, Record::DataEnd(_) | Record::Footer(_)));
                Some(records)
            }
            None => {
                self.done = true;
                None
            }
        }
    }
}

/// Writes the complete records of the cut-off `bytes` to `out` as a whole MCAP file, synced.
fn rewrite(bytes: &[u8], out: &Path) -> Result<Recovered, String> {
    let mut walk = Walk::new(bytes);
    let mut unit = walk.next();
    // The header comes first: its profile is kept, and its library named.
    let (profile, library) = match unit.as_deref() {
        Some([Record::Header(h)]) => (h.profile.clone(), h.library.clone()),
        _ => (String::new(), String::new()),
    };
    let recovered_by = format!("recovered by road-serve {}", env!("CARGO_PKG_VERSION"));
    let library = if library.is_empty() {
        recovered_by
    } else {
        format!("{library}; {recovered_by}")
    };
    let write_err = |e: &dyn std::fmt::Display| format!("cannot write {}: {e}", out.display());
    let file = File::create(out).map_err(|e| write_err(&e))?;
    let mut writer = mcap::WriteOptions::new()
        .compression(Some(mcap::Compression::Zstd))
        .profile(profile)
        .library(library)
        .create(BufWriter::new(file))
        .map_err(|e| write_err(&e))?;
    let mut schemas = BTreeSet::new();
    let mut channels = BTreeSet::new();
    let mut messages = 0u64;
    let mut kept = mcap::MAGIC.len();
    while let Some(records) = unit {
        // A unit that names a schema or channel not defined before it is damage: the walk
        // ends before it, as at a cut.
        if !references_known(&records, &schemas, &channels) {
            break;
        }
        for record in records {
            match record {
                Record::Schema { header, data } => {
                    writer
                        .add_schema_with_id(header.id, &header.name, &header.encoding, &data)
                        .map_err(|e| write_err(&e))?;
                    schemas.insert(header.id);
                }
                Record::Channel(ch) => {
                    writer
                        .add_channel_with_id(
                            ch.id,
                            ch.schema_id,
                            &ch.topic,
                            &ch.message_encoding,
                            &ch.metadata,
                        )
                        .map_err(|e| write_err(&e))?;
                    channels.insert(ch.id);
                }
                Record::Message { header, data } => {
                    writer
                        .write_to_known_channel(&header, &data)
                        .map_err(|e| write_err(&e))?;
                    messages += 1;
                }
                Record::Attachment { header, data, .. } => writer
                    .attach(&mcap::Attachment {
                        log_time: header.log_time,
                        create_time: header.create_time,
                        name: header.name,
                        media_type: header.media_type,
                        data,
                    })
                    .map_err(|e| write_err(&e))?,
                Record::Metadata(m) => writer.write_metadata(&m).map_err(|e| write_err(&e))?,
                // Indexes, statistics and the like are written anew by the writer.
                _ => {}
            }
        }
        kept = walk.pos;
        unit = walk.next();
    }
    writer.finish().map_err(|e| write_err(&e))?;
    let file = writer
        .into_inner()
        .into_inner()
        .map_err(|e| write_err(&e.into_error()))?;
    file.sync_all().map_err(|e| write_err(&e))?;
    drop(file);
    // Read back as the default readers do before it replaces anything.
    let written = std::fs::read(out).map_err(|e| write_err(&e))?;
    let read_back =
        |e: &dyn std::fmt::Display| format!("{} does not read back: {e}", out.display());
    let summary_found = mcap::Summary::read(&written)
        .map_err(|e| read_back(&e))?
        .is_some();
    let read = mcap::MessageStream::new(&written)
        .and_then(|stream| stream.collect::<McapResult<Vec<_>>>())
        .map_err(|e| read_back(&e))?
        .len() as u64;
    if !summary_found || read != messages {
        return Err(read_back(&format!(
            "summary {}, {read} messages of {messages}",
            if summary_found { "found" } else { "missing" }
        )));
    }
    Ok(Recovered {
        messages,
        kept_bytes: kept as u64,
        dropped_bytes: (bytes.len() - kept) as u64,
    })
}

/// Whether every channel and message of `records` names a schema or channel defined before
/// it (in `records` or in the sets).
fn references_known(
    records: &[Record<'_>],
    schemas: &BTreeSet<u16>,
    channels: &BTreeSet<u16>,
) -> bool {
    let (mut schemas, mut channels) = (schemas.clone(), channels.clone());
    records.iter().all(|r| match r {
        Record::Schema { header, .. } => {
            schemas.insert(header.id);
            true
        }
        Record::Channel(ch) => {
            channels.insert(ch.id);
            ch.schema_id == 0 || schemas.contains(&ch.schema_id)
        }
        Record::Message { header, .. } => channels.contains(&header.channel_id),
        _ => true,
    })
}

#[cfg(test)]
mod tests {
    use std::time::{Duration, SystemTime};

    use super::*;
    use crate::record::{Recorder, topics};

    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("road-recover-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    /// A recording of `rounds` flushes of three messages each (after the creation's two):
    /// the bytes a killed server leaves after its last flush, and the finished file.
    fn recording(dir: &Path, rounds: u64) -> (Vec<u8>, Vec<u8>) {
        let t0 = SystemTime::UNIX_EPOCH + Duration::from_secs(1_700_000_000);
        let mut rec =
            Recorder::start(dir, 1, b"{\"create\":1}", b"{\"scene\":1}", None, t0).unwrap();
        for t in 1..=rounds {
            let at = t0 + Duration::from_millis(100 * t);
            for topic in [topics::EGO, topics::NPC, topics::AGENTS] {
                let data = format!(
                    "{{\"tick\":{t},\"pad\":\"{}\"}}",
                    "x".repeat(64 * t as usize)
                );
                rec.write(topic, data.as_bytes(), at).unwrap();
            }
            rec.flush().unwrap();
        }
        let cut = std::fs::read(rec.path()).unwrap();
        let path = rec.finish().unwrap();
        let whole = std::fs::read(&path).unwrap();
        std::fs::remove_file(&path).unwrap();
        (cut, whole)
    }

    /// (channel topic, sequence, log time, data) of every message, read as the default
    /// readers read (the file must be whole: a summary, no error).
    fn read_whole(bytes: &[u8]) -> Vec<(String, u32, u64, Vec<u8>)> {
        assert!(mcap::Summary::read(bytes).unwrap().is_some(), "no summary");
        mcap::MessageStream::new(bytes)
            .unwrap()
            .map(|m| {
                let m = m.unwrap();
                (
                    m.channel.topic.clone(),
                    m.sequence,
                    m.log_time,
                    m.data.into_owned(),
                )
            })
            .collect()
    }

    #[test]
    fn a_cut_off_file_recovers_to_the_complete_messages_before_the_cut() {
        let dir = temp_dir("cuts");
        let (killed, whole) = recording(&dir, 4);
        let all = read_whole(&whole);
        assert_eq!(all.len(), 2 + 4 * 3);
        // What the killed file holds is the finished file's data section.
        assert!(whole.starts_with(&killed));
        assert!(!ends_with_footer(&killed));
        // Each chunk's end, and how many messages the chunks up to it hold, from the index.
        let summary = mcap::Summary::read(&whole).unwrap().unwrap();
        let mut chunks: Vec<_> = summary.chunk_indexes.clone();
        chunks.sort_by_key(|c| c.chunk_start_offset);
        assert_eq!(chunks.len(), 5);
        let mut ends = Vec::new();
        let mut total = 0;
        for c in &chunks {
            total += summary.stream_chunk(&whole, c).unwrap().count();
            ends.push(((c.chunk_start_offset + c.chunk_length) as usize, total));
        }
        let expected_at = |cut: usize| {
            ends.iter()
                .filter(|(end, _)| *end <= cut)
                .map(|(_, n)| *n)
                .max()
                .unwrap_or(0)
        };
        let mut cuts = vec![8, 9, 20, killed.len(), whole.len() - 1, whole.len() - 9];
        for c in &chunks {
            let (start, end) = (
                c.chunk_start_offset as usize,
                (c.chunk_start_offset + c.chunk_length) as usize,
            );
            cuts.extend([
                start,
                start + 1,
                start + 9,
                (start + end) / 2,
                end - 1,
                end,
                end + 3,
            ]);
        }
        let path = dir.join("scene-1.mcap");
        let mut seen = BTreeSet::new();
        for cut in cuts {
            std::fs::write(&path, &whole[..cut]).unwrap();
            let Recovery::Recovered(r) = recover(&path).unwrap() else {
                panic!("cut at {cut}: not recovered");
            };
            // A cut in the summary keeps every message.
            let expected = if cut >= killed.len() {
                all.len()
            } else {
                expected_at(cut)
            };
            assert_eq!(r.messages as usize, expected, "cut at {cut}");
            seen.insert(expected);
            assert_eq!(r.kept_bytes + r.dropped_bytes, cut as u64, "cut at {cut}");
            let recovered = std::fs::read(&path).unwrap();
            assert_eq!(read_whole(&recovered), all[..expected], "cut at {cut}");
            assert!(!recovering_path(&path).exists());
            assert_eq!(recover(&path).unwrap(), Recovery::Complete, "cut at {cut}");
            assert_eq!(std::fs::read(&path).unwrap(), recovered);
        }
        // Every chunk's end was a cut's boundary: nothing, the creation, and each flush.
        assert_eq!(seen.into_iter().collect::<Vec<_>>(), [0, 2, 5, 8, 11, 14]);
        // What a writer leaves when killed inside a chunk it streams to the file: the chunk's
        // placeholder length (all ones), which the standard readers refuse as too long.
        let start = chunks[2].chunk_start_offset as usize;
        let mut partial = whole[..start + 40].to_vec();
        partial[start + 1..start + 9].copy_from_slice(&u64::MAX.to_le_bytes());
        std::fs::write(&path, &partial).unwrap();
        let Recovery::Recovered(r) = recover(&path).unwrap() else {
            panic!("not recovered");
        };
        assert_eq!(r.messages as usize, expected_at(start));
        assert_eq!(r.dropped_bytes, 40);
        assert_eq!(
            read_whole(&std::fs::read(&path).unwrap()),
            all[..expected_at(start)]
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_cut_before_the_first_record_or_garbage_is_an_error_naming_the_file() {
        let dir = temp_dir("garbage");
        for (name, bytes) in [
            (
                "scene-1.mcap",
                b"not an mcap file at all, just text".to_vec(),
            ),
            ("scene-2.mcap", mcap::MAGIC[..3].to_vec()),
            ("scene-3.mcap", Vec::new()),
        ] {
            let path = dir.join(name);
            std::fs::write(&path, &bytes).unwrap();
            let err = recover(&path).unwrap_err();
            assert!(matches!(err, Error::Recover { .. }), "{err}");
            assert!(
                err.to_string().contains(&path.display().to_string()),
                "{err}"
            );
            assert_eq!(std::fs::read(&path).unwrap(), bytes);
            assert!(!recovering_path(&path).exists());
        }
        let missing = dir.join("scene-4.mcap");
        let err = recover(&missing).unwrap_err();
        assert!(err.to_string().contains("scene-4.mcap"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_complete_file_is_left_untouched() {
        let dir = temp_dir("complete");
        let (_, whole) = recording(&dir, 2);
        let path = dir.join("scene-1.mcap");
        std::fs::write(&path, &whole).unwrap();
        let modified = std::fs::metadata(&path).unwrap().modified().unwrap();
        assert!(has_footer(&path).unwrap());
        assert_eq!(recover(&path).unwrap(), Recovery::Complete);
        assert_eq!(std::fs::read(&path).unwrap(), whole);
        assert_eq!(
            std::fs::metadata(&path).unwrap().modified().unwrap(),
            modified
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_recording_being_written_is_left_alone() {
        let dir = temp_dir("live");
        let t0 = SystemTime::UNIX_EPOCH + Duration::from_secs(1_700_000_000);
        let mut rec = Recorder::start(&dir, 1, b"{}", b"{}", None, t0).unwrap();
        rec.flush().unwrap();
        let before = std::fs::read(rec.path()).unwrap();
        let err = recover(rec.path()).unwrap_err();
        assert!(matches!(err, Error::RecordingInUse { .. }), "{err}");
        assert_eq!(std::fs::read(rec.path()).unwrap(), before);
        assert!(recover_folder(&dir)[0].1.is_err());
        rec.finish().unwrap();
        // Finished: nothing to do.
        assert!(recover_folder(&dir).is_empty());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_folder_recovers_the_servers_own_cut_off_files_only() {
        let dir = temp_dir("folder");
        let (killed, whole) = recording(&dir, 2);
        for name in [
            "scene-1.mcap",
            "scene-2-2.mcap",
            "notes.mcap",
            "scene-x.mcap",
        ] {
            std::fs::write(dir.join(name), &killed).unwrap();
        }
        std::fs::write(dir.join("scene-3.mcap"), &whole).unwrap();
        std::fs::write(dir.join("scene-4.mcap"), b"garbage").unwrap();
        let outcomes = recover_folder(&dir);
        let names: Vec<String> = outcomes
            .iter()
            .map(|(p, _)| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["scene-1.mcap", "scene-2-2.mcap", "scene-4.mcap"]);
        assert!(matches!(outcomes[0].1, Ok(Recovery::Recovered(r)) if r.messages == 8));
        assert!(matches!(outcomes[1].1, Ok(Recovery::Recovered(_))));
        assert!(outcomes[2].1.is_err());
        for name in ["scene-1.mcap", "scene-2-2.mcap"] {
            assert!(has_footer(&dir.join(name)).unwrap(), "{name}");
        }
        for name in ["notes.mcap", "scene-x.mcap"] {
            assert_eq!(std::fs::read(dir.join(name)).unwrap(), killed, "{name}");
        }
        assert_eq!(std::fs::read(dir.join("scene-3.mcap")).unwrap(), whole);
        assert!(recover_folder(&dir.join("missing")).is_empty());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn recording_names_are_the_writers() {
        for name in ["scene-1.mcap", "scene-42-2.mcap", "scene-7-13.mcap"] {
            assert!(is_recording_name(name), "{name}");
        }
        for name in [
            "scene-.mcap",
            "scene-1.mcap.recovering",
            "scene-1-.mcap",
            "scene-a.mcap",
            "scene-1-2-3.mcap",
            "demo.mcap",
            "xscene-1.mcap",
        ] {
            assert!(!is_recording_name(name), "{name}");
        }
    }
}
