//! INTERACTION track files (`vehicle_tracks_NNN.csv` or `.csv.gz`).

use std::io::Read;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::{Error, Result};

/// The column layout this reader accepts, in order.
pub const TRACK_COLUMNS: [&str; 11] = [
    "track_id",
    "frame_id",
    "timestamp_ms",
    "agent_type",
    "x",
    "y",
    "vx",
    "vy",
    "psi_rad",
    "length",
    "width",
];

/// Recording rate of every INTERACTION file.
pub const STEP_SECS: f64 = 0.1;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum AgentType {
    Car,
    Truck,
    Bicycle,
    Pedestrian,
}

impl AgentType {
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "car" => Some(Self::Car),
            "truck" | "bus" => Some(Self::Truck),
            "bicycle" => Some(Self::Bicycle),
            "pedestrian" | "pedestrian/bicycle" => Some(Self::Pedestrian),
            _ => None,
        }
    }

    /// Dense index for embeddings.
    pub fn index(self) -> u8 {
        self as u8
    }
}

/// One agent's contiguous track. `states` holds `[x_m, y_m, heading_rad]` per frame from
/// `first_frame` on (velocities are not kept: the model works on poses).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Track {
    pub track_id: u32,
    pub agent_type: AgentType,
    pub length_m: f32,
    pub width_m: f32,
    pub first_frame: u32,
    pub states: Vec<[f32; 3]>, // [frames, (x_m, y_m, heading_rad)]
}

impl Track {
    pub fn last_frame(&self) -> u32 {
        self.first_frame + self.states.len() as u32 - 1
    }

    /// State at `frame`, if the track covers it.
    pub fn state_at(&self, frame: u32) -> Option<[f32; 3]> {
        frame
            .checked_sub(self.first_frame)
            .and_then(|i| self.states.get(i as usize))
            .copied()
    }
}

/// One file: one continuous recording.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Recording {
    pub location: String,
    /// File name without directories, e.g. `vehicle_tracks_000.csv.gz`.
    pub file: String,
    pub tracks: Vec<Track>,
    pub first_frame: u32,
    pub last_frame: u32,
}

impl Recording {
    pub fn duration_secs(&self) -> f64 {
        f64::from(self.last_frame - self.first_frame + 1) * STEP_SECS
    }

    pub fn load(path: &Path, location: &str) -> Result<Self> {
        let file = std::fs::File::open(path).map_err(|source| Error::io(path, source))?;
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        if name.ends_with(".gz") {
            let mut text = String::new();
            flate2::read::GzDecoder::new(file)
                .read_to_string(&mut text)
                .map_err(|source| Error::io(path, source))?;
            Self::parse(text.as_bytes(), path, location)
        } else {
            Self::parse(std::io::BufReader::new(file), path, location)
        }
    }

    /// Parses CSV text; `path` only names the input in errors.
    pub fn parse(reader: impl Read, path: &Path, location: &str) -> Result<Self> {
        let row_err = |line: u64, reason: String| Error::Track {
            path: path.to_owned(),
            line,
            reason,
        };
        let mut csv = csv::ReaderBuilder::new()
            .has_headers(true)
            .from_reader(reader);
        let header = csv
            .headers()
            .map_err(|e| row_err(1, e.to_string()))?
            .clone();
        if header
            .iter()
            .map(str::trim)
            .ne(TRACK_COLUMNS.iter().copied())
        {
            return Err(Error::Columns {
                path: path.to_owned(),
                expected: TRACK_COLUMNS.join(","),
                found: header.iter().collect::<Vec<_>>().join(","),
            });
        }
        let mut tracks: Vec<Track> = Vec::new();
        let mut record = csv::StringRecord::new();
        loop {
            match csv.read_record(&mut record) {
                Ok(false) => break,
                Ok(true) => {}
                Err(e) => {
                    let line = e.position().map_or(0, |p| p.line());
                    return Err(row_err(line, e.to_string()));
                }
            }
            let line = record.position().map_or(0, |p| p.line());
            let field = |i: usize| record.get(i).unwrap_or("").trim();
            let int = |i: usize| -> Result<u32> {
                field(i).parse().map_err(|_| {
                    row_err(
                        line,
                        format!("{} is not an integer: `{}`", TRACK_COLUMNS[i], field(i)),
                    )
                })
            };
            let real = |i: usize| -> Result<f64> {
                match field(i).parse::<f64>() {
                    Ok(v) if v.is_finite() => Ok(v),
                    _ => Err(row_err(
                        line,
                        format!(
                            "{} is not a finite number: `{}`",
                            TRACK_COLUMNS[i],
                            field(i)
                        ),
                    )),
                }
            };
            let (track_id, frame) = (int(0)?, int(1)?);
            let agent_type = AgentType::parse(field(3))
                .ok_or_else(|| row_err(line, format!("unknown agent_type `{}`", field(3))))?;
            let (x, y, psi, length, width) = (real(4)?, real(5)?, real(8)?, real(9)?, real(10)?);
            if length <= 0.0 || width <= 0.0 {
                return Err(row_err(
                    line,
                    format!("agent size must be positive, got length {length} width {width}"),
                ));
            }
            let state = [x as f32, y as f32, psi as f32];
            match tracks.last_mut() {
                Some(t) if t.track_id == track_id => {
                    let expected = t.last_frame() + 1;
                    if frame != expected {
                        return Err(row_err(
                            line,
                            format!(
                                "track {track_id} jumps from frame {} to {frame}: frames must be contiguous",
                                expected - 1
                            ),
                        ));
                    }
                    t.states.push(state);
                }
                _ => {
                    if tracks.iter().any(|t| t.track_id == track_id) {
                        return Err(row_err(
                            line,
                            format!("track {track_id} appears again after other tracks"),
                        ));
                    }
                    tracks.push(Track {
                        track_id,
                        agent_type,
                        length_m: length as f32,
                        width_m: width as f32,
                        first_frame: frame,
                        states: vec![state],
                    });
                }
            }
        }
        if tracks.is_empty() {
            return Err(row_err(1, "no rows".into()));
        }
        let first_frame = tracks.iter().map(|t| t.first_frame).min().unwrap_or(0);
        let last_frame = tracks.iter().map(Track::last_frame).max().unwrap_or(0);
        let file = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        Ok(Self {
            location: location.to_owned(),
            file,
            tracks,
            first_frame,
            last_frame,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HEADER: &str =
        "track_id,frame_id,timestamp_ms,agent_type,x,y,vx,vy,psi_rad,length,width\n";

    fn parse(body: &str) -> Result<Recording> {
        Recording::parse(
            format!("{HEADER}{body}").as_bytes(),
            Path::new("t.csv"),
            "LOC",
        )
    }

    #[test]
    fn parses_tracks() {
        let r = parse("1,1,100,car,1.0,2.0,0,0,0.5,4.0,1.8\n1,2,200,car,1.5,2.0,0,0,0.5,4.0,1.8\n2,2,200,car,9,9,0,0,-3,4.5,2\n")
            .unwrap();
        assert_eq!(r.tracks.len(), 2);
        assert_eq!(r.tracks[0].states, vec![[1.0, 2.0, 0.5], [1.5, 2.0, 0.5]]);
        assert_eq!((r.first_frame, r.last_frame), (1, 2));
        assert_eq!(r.tracks[1].state_at(2), Some([9.0, 9.0, -3.0]));
        assert_eq!(r.tracks[1].state_at(1), None);
        assert!((r.duration_secs() - 0.2).abs() < 1e-12);
    }

    #[test]
    fn bad_rows_name_file_and_line() {
        let e = parse("1,1,100,car,1.0,2.0,0,0,0.5,4.0,1.8\n1,2,200,car,NaN,2.0,0,0,0.5,4.0,1.8\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("t.csv:3") && e.contains("x is not a finite number"),
            "{e}"
        );
        let e = parse("1,1,100,car,1.0,2.0,0,0\n").unwrap_err().to_string();
        assert!(e.contains("t.csv:2"), "{e}");
        let e = parse("1,1,100,tank,1.0,2.0,0,0,0.5,4.0,1.8\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("unknown agent_type `tank`") && e.contains("t.csv:2"),
            "{e}"
        );
        let e = parse("1,1,100,car,1,2,0,0,0.5,4,1.8\n1,3,300,car,1,2,0,0,0.5,4,1.8\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("jumps from frame 1 to 3") && e.contains("t.csv:3"),
            "{e}"
        );
        let e = Recording::parse("a,b,c\n1,2,3\n".as_bytes(), Path::new("t.csv"), "LOC")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("unknown column layout") && e.contains("a,b,c"),
            "{e}"
        );
    }
}
