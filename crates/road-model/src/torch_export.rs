//! The training data as flat arrays for the PyTorch training path (`scripts/torch_train.py`),
//! `docs/torch-training.md`.
//!
//! A split is written as it is cached: recordings' track states, the maps' lanelet centre lines
//! (resampled as [`Dataset::window`] resamples them) and the window index, not materialised
//! windows, so that both splits stay near the size of the `*.roadds` caches and fit what a
//! lent GPU machine can be sent. Python materialises exactly the [`road_data::SceneWindow`]s
//! Rust does (same f64 normalisation, same f32 heading unwrapping).
//!
//! With a run config, the run's fixed validation batches ([`crate::train::validation_batches`],
//! collated) can be written too, so that the PyTorch run's validation losses are those `road
//! train` would log for the same weights.

use std::borrow::Cow;
use std::collections::HashMap;
use std::path::Path;

use candle_core::Device;
use road_data::Dataset;
use road_data::geometry::resample;
use safetensors::{Dtype, View};

use crate::config::RunConfig;
use crate::{Error, Result};

/// `format` in every file's metadata.
pub const FORMAT: &str = "road-torch-dataset";
/// Bump on any change to the arrays' names, types or meaning.
pub const FORMAT_VERSION: u32 = 1;
/// `format` of the validation batches' file.
pub const BATCHES_FORMAT: &str = "road-torch-validation-batches";

/// One owned little-endian array.
#[derive(Debug, Clone, PartialEq)]
pub struct Array {
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    pub bytes: Vec<u8>,
}

macro_rules! array_from {
    ($name:ident, $t:ty, $dtype:expr) => {
        pub fn $name(values: &[$t], shape: &[usize]) -> Self {
            assert_eq!(
                values.len(),
                shape.iter().product::<usize>(),
                "array shape {shape:?} does not hold {} values",
                values.len()
            );
            Self {
                dtype: $dtype,
                shape: shape.to_vec(),
                bytes: values.iter().flat_map(|v| v.to_le_bytes()).collect(),
            }
        }
    };
}

impl Array {
    array_from!(u8s, u8, Dtype::U8);
    array_from!(u16s, u16, Dtype::U16);
    array_from!(u32s, u32, Dtype::U32);
    array_from!(i64s, i64, Dtype::I64);
    array_from!(f32s, f32, Dtype::F32);
    array_from!(f64s, f64, Dtype::F64);
}

impl View for &Array {
    fn dtype(&self) -> Dtype {
        self.dtype
    }

    fn shape(&self) -> &[usize] {
        &self.shape
    }

    fn data(&self) -> Cow<'_, [u8]> {
        Cow::Borrowed(&self.bytes)
    }

    fn data_len(&self) -> usize {
        self.bytes.len()
    }
}

/// Named arrays and string metadata: one safetensors file.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ArrayFile {
    pub arrays: Vec<(String, Array)>,
    pub metadata: HashMap<String, String>,
}

impl ArrayFile {
    fn push(&mut self, name: &str, array: Array) {
        self.arrays.push((name.to_owned(), array));
    }

    pub fn get(&self, name: &str) -> Option<&Array> {
        self.arrays.iter().find(|(n, _)| n == name).map(|(_, a)| a)
    }

    /// Writes atomically (temporary file, then rename); returns the file's size in bytes.
    pub fn save(&self, path: &Path) -> Result<u64> {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        }
        let tmp = path.with_extension("tmp");
        safetensors::serialize_to_file(
            self.arrays.iter().map(|(n, a)| (n.as_str(), a)),
            Some(self.metadata.clone()),
            &tmp,
        )
        .map_err(|e| Error::Checkpoint {
            path: tmp.clone(),
            reason: format!("cannot write safetensors: {e}"),
        })?;
        std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))?;
        Ok(std::fs::metadata(path)
            .map_err(|e| Error::io(path, e))?
            .len())
    }

    /// Reads a file written by [`Self::save`] (any safetensors file).
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let bad = |reason: String| Error::Checkpoint {
            path: path.to_owned(),
            reason,
        };
        let (_, header) = safetensors::SafeTensors::read_metadata(&bytes)
            .map_err(|e| bad(format!("not a safetensors file: {e}")))?;
        let metadata = header.metadata().clone().unwrap_or_default();
        let tensors = safetensors::SafeTensors::deserialize(&bytes)
            .map_err(|e| bad(format!("not a safetensors file: {e}")))?;
        let mut arrays: Vec<(String, Array)> = tensors
            .tensors()
            .into_iter()
            .map(|(name, view)| {
                (
                    name,
                    Array {
                        dtype: view.dtype(),
                        shape: view.shape().to_vec(),
                        bytes: view.data().to_vec(),
                    },
                )
            })
            .collect();
        arrays.sort_by(|a, b| a.0.cmp(&b.0));
        Ok(Self { arrays, metadata })
    }
}

fn too_many(what: &str, count: usize, limit: usize) -> Error {
    Error::data(format!(
        "the torch export stores {what} in {limit}-value integers, but the dataset has {count}"
    ))
}

/// How `track_states_packed` holds the `[frames, 3]` f32 states: their bit patterns as u32,
/// differenced along the frames per column (wrapping; the first row kept), split into byte
/// planes (column-major: column 0 byte 0 of every frame, then column 0 byte 1, …, little
/// endian bytes) and zlib-compressed. Lossless, and a quarter of the raw size: consecutive
/// poses share their high bytes. Python: `np.cumsum(deltas, axis=0, dtype=np.uint32)`.
pub const STATES_ENCODING: &str = "u32-delta-byteplanes-zlib";

/// [`STATES_ENCODING`] of `[frames, 3]` states.
pub fn pack_states(states: &[f32]) -> Result<Vec<u8>> {
    use std::io::Write;
    let frames = states.len() / 3;
    let bits: Vec<u32> = states.iter().map(|v| v.to_bits()).collect();
    let mut planes = vec![0u8; frames * 12];
    for column in 0..3 {
        let mut previous = 0u32;
        for frame in 0..frames {
            let value = bits[frame * 3 + column];
            let delta = value.wrapping_sub(previous).to_le_bytes();
            previous = value;
            for (byte, &b) in delta.iter().enumerate() {
                planes[(column * 4 + byte) * frames + frame] = b;
            }
        }
    }
    let mut encoder = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::new(6));
    encoder
        .write_all(&planes)
        .and_then(|()| encoder.finish())
        .map_err(|e| Error::data(format!("cannot compress the track states: {e}")))
}

/// Offsets `[n + 1]` of consecutive runs of the given lengths.
fn offsets(lengths: impl Iterator<Item = usize>) -> Vec<i64> {
    let mut out = vec![0i64];
    for len in lengths {
        let last = *out.last().expect("starts with 0");
        out.push(last + len as i64);
    }
    out
}

/// A split as flat arrays (names and meaning in `docs/torch-training.md`):
///
/// - tracks of every recording, concatenated: `track_offsets [T + 1]` into the states
///   `[frames, 3]` (x_m, y_m, heading_rad as parsed, f32; stored as `track_states_packed`,
///   [`STATES_ENCODING`]), `track_first_frame`,
///   `track_type` (car, truck, bicycle, pedestrian = 0..3), `track_length_m`, `track_width_m`,
///   `track_id`; `recording_track_offsets [R + 1]` into them, `recording_map [R]`;
/// - lanelet centre lines of every map, resampled to the window config's `polyline_points` in
///   metres (f64, as [`Dataset::window`] resamples them): `lanelet_centres [L, Q, 2]`,
///   `lanelet_id [L]`, `map_lanelet_offsets [M + 1]`;
/// - windows: `window_recording`, `window_start_frame`, `window_origin_m [N, 2]` (f64),
///   `window_agent_offsets [N + 1]` into `window_agents` (track index within the recording,
///   nearest the centre first), `window_polyline_offsets [N + 1]` into `window_polylines`
///   (lanelet index within the map, nearest first).
pub fn dataset_arrays(ds: &Dataset) -> Result<ArrayFile> {
    let q = ds.config.polyline_points;
    let mut file = ArrayFile::default();
    let tracks: Vec<&road_data::Track> = ds.recordings.iter().flat_map(|r| &r.tracks).collect();
    let states: Vec<f32> = tracks
        .iter()
        .flat_map(|t| t.states.iter().flatten().copied())
        .collect();
    let packed = pack_states(&states)?;
    file.push("track_states_packed", Array::u8s(&packed, &[packed.len()]));
    let frames = states.len() / 3;
    let t = tracks.len();
    file.push(
        "track_offsets",
        Array::i64s(&offsets(tracks.iter().map(|t| t.states.len())), &[t + 1]),
    );
    let first: Vec<u32> = tracks.iter().map(|t| t.first_frame).collect();
    file.push("track_first_frame", Array::u32s(&first, &[t]));
    let types: Vec<u8> = tracks.iter().map(|t| t.agent_type.index()).collect();
    file.push("track_type", Array::u8s(&types, &[t]));
    let length: Vec<f32> = tracks.iter().map(|t| t.length_m).collect();
    file.push("track_length_m", Array::f32s(&length, &[t]));
    let width: Vec<f32> = tracks.iter().map(|t| t.width_m).collect();
    file.push("track_width_m", Array::f32s(&width, &[t]));
    let ids: Vec<u32> = tracks.iter().map(|t| t.track_id).collect();
    file.push("track_id", Array::u32s(&ids, &[t]));
    let r = ds.recordings.len();
    file.push(
        "recording_track_offsets",
        Array::i64s(
            &offsets(ds.recordings.iter().map(|r| r.tracks.len())),
            &[r + 1],
        ),
    );
    file.push("recording_map", Array::u32s(&ds.recording_map, &[r]));

    let mut centres: Vec<f64> = Vec::new();
    let mut lanelet_ids: Vec<i64> = Vec::new();
    for map in &ds.maps {
        for lanelet in &map.lanelets {
            let points = resample(&lanelet.centre_m, q);
            if points.len() != q {
                return Err(Error::data(format!(
                    "lanelet {} of the {} map has no centre line",
                    lanelet.id, map.location
                )));
            }
            centres.extend(points.iter().flatten());
            lanelet_ids.push(lanelet.id);
        }
    }
    let l = lanelet_ids.len();
    file.push("lanelet_centres", Array::f64s(&centres, &[l, q, 2]));
    file.push("lanelet_id", Array::i64s(&lanelet_ids, &[l]));
    file.push(
        "map_lanelet_offsets",
        Array::i64s(
            &offsets(ds.maps.iter().map(|m| m.lanelets.len())),
            &[ds.maps.len() + 1],
        ),
    );

    let n = ds.windows.len();
    let recording: Vec<u32> = ds.windows.iter().map(|w| w.recording).collect();
    file.push("window_recording", Array::u32s(&recording, &[n]));
    let start: Vec<u32> = ds.windows.iter().map(|w| w.start_frame).collect();
    file.push("window_start_frame", Array::u32s(&start, &[n]));
    let origin: Vec<f64> = ds.windows.iter().flat_map(|w| w.origin_m).collect();
    file.push("window_origin_m", Array::f64s(&origin, &[n, 2]));
    let most_tracks = ds
        .recordings
        .iter()
        .map(|r| r.tracks.len())
        .max()
        .unwrap_or(0);
    if most_tracks > usize::from(u16::MAX) + 1 {
        return Err(too_many("track indices", most_tracks, 1 << 16));
    }
    let agents: Vec<u16> = ds
        .windows
        .iter()
        .flat_map(|w| w.agents.iter().map(|&a| a as u16))
        .collect();
    file.push(
        "window_agent_offsets",
        Array::i64s(
            &offsets(ds.windows.iter().map(|w| w.agents.len())),
            &[n + 1],
        ),
    );
    file.push("window_agents", Array::u16s(&agents, &[agents.len()]));
    // Lanelet indices are the bulk of the index (up to max_polylines per window): 16 bits.
    let most_lanelets = ds.maps.iter().map(|m| m.lanelets.len()).max().unwrap_or(0);
    if most_lanelets > usize::from(u16::MAX) + 1 {
        return Err(too_many("lanelet indices", most_lanelets, 1 << 16));
    }
    let polylines: Vec<u16> = ds
        .windows
        .iter()
        .flat_map(|w| w.polylines.iter().map(|&p| p as u16))
        .collect();
    file.push(
        "window_polyline_offsets",
        Array::i64s(
            &offsets(ds.windows.iter().map(|w| w.polylines.len())),
            &[n + 1],
        ),
    );
    file.push(
        "window_polylines",
        Array::u16s(&polylines, &[polylines.len()]),
    );

    let window_config = toml::to_string(&ds.config)
        .map_err(|e| Error::data(format!("cannot write the window config as TOML: {e}")))?;
    file.metadata = HashMap::from([
        ("format".to_owned(), FORMAT.to_owned()),
        ("format_version".to_owned(), FORMAT_VERSION.to_string()),
        ("split".to_owned(), ds.split.name().to_owned()),
        ("windows".to_owned(), n.to_string()),
        ("window_config".to_owned(), window_config),
        ("track_states_shape".to_owned(), format!("{frames},3")),
        (
            "track_states_encoding".to_owned(),
            STATES_ENCODING.to_owned(),
        ),
        (
            "locations".to_owned(),
            ds.maps
                .iter()
                .map(|m| m.location.as_str())
                .collect::<Vec<_>>()
                .join(","),
        ),
    ]);
    Ok(file)
}

/// The run's fixed validation batches (what `road train` validates on), collated:
/// `batch{i}.{x0, x_noisy, sigma, valid, agent_features, map, map_valid}` (f32, the shapes of
/// [`crate::batch::Batch`]). The metadata names the run keys they depend on.
pub fn validation_batch_arrays(run: &RunConfig, validation_set: &Dataset) -> Result<ArrayFile> {
    let batches = crate::train::validation_batches(run, validation_set, &Device::Cpu)?;
    let mut file = ArrayFile::default();
    for (i, batch) in batches.iter().enumerate() {
        for (name, tensor) in batch.named_tensors() {
            let values = tensor.flatten_all()?.to_vec1::<f32>()?;
            file.push(
                &format!("batch{i}.{name}"),
                Array::f32s(&values, tensor.dims()),
            );
        }
    }
    let t = &run.train;
    file.metadata = HashMap::from([
        ("format".to_owned(), BATCHES_FORMAT.to_owned()),
        ("format_version".to_owned(), FORMAT_VERSION.to_string()),
        ("batches".to_owned(), batches.len().to_string()),
        ("batch_scenes".to_owned(), t.batch_scenes.to_string()),
        (
            "window_slots".to_owned(),
            run.model.window_slots.to_string(),
        ),
        ("obs_slots".to_owned(), run.planner.obs_slots.to_string()),
        (
            "map_polylines".to_owned(),
            run.model.map_polylines.to_string(),
        ),
        (
            "heading_scale".to_owned(),
            run.model.heading_scale.to_string(),
        ),
        (
            "augmentation_ratio".to_owned(),
            t.augmentation_ratio.to_string(),
        ),
        (
            "warmup_task_prob".to_owned(),
            t.warmup_task_prob.to_string(),
        ),
        (
            "validation_windows".to_owned(),
            validation_set.len().to_string(),
        ),
        ("run".to_owned(), run.name.clone()),
    ]);
    Ok(file)
}
