//! Config files with per-key command-line overrides (`--set key=value`).

use std::path::Path;

use anyhow::{Context, Result, bail};
use serde::Serialize;
use serde::de::DeserializeOwned;

/// Loads `T` from `file` (or from `T::default()` when absent), then applies `key=value`
/// overrides; values are TOML (`40`, `0.5`, `"text"`), bare words are taken as strings.
/// Dotted keys reach into tables (`edm.sigma_max=60`).
pub fn load<T: DeserializeOwned + Serialize + Default>(
    file: Option<&Path>,
    overrides: &[String],
) -> Result<T> {
    let (mut table, origin) = match file {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("cannot read config {}", path.display()))?;
            let table: toml::Table =
                toml::from_str(&text).with_context(|| format!("bad config {}", path.display()))?;
            (table, path.display().to_string())
        }
        None => (
            toml::Table::try_from(T::default()).context("cannot serialise the default config")?,
            "defaults".to_owned(),
        ),
    };
    for item in overrides {
        let Some((key, raw)) = item.split_once('=') else {
            bail!("an override must look like key=value, got `{item}`");
        };
        let value: toml::Value = toml::from_str::<toml::Table>(&format!("v = {raw}"))
            .ok()
            .and_then(|mut t| t.remove("v"))
            .unwrap_or_else(|| toml::Value::String(raw.to_owned()));
        let mut target = &mut table;
        let parts: Vec<&str> = key.split('.').collect();
        for part in &parts[..parts.len() - 1] {
            target = target
                .entry(part.to_string())
                .or_insert_with(|| toml::Value::Table(toml::Table::new()))
                .as_table_mut()
                .with_context(|| format!("override `{item}`: `{part}` is not a table"))?;
        }
        target.insert(parts[parts.len() - 1].to_owned(), value);
    }
    T::deserialize(toml::Value::Table(table))
        .with_context(|| format!("bad config ({origin} with overrides {overrides:?})"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overrides_apply_and_unknown_keys_fail() {
        let c: road_data::WindowConfig = load(
            None,
            &["window_steps=20".into(), "position_scale_m=25.5".into()],
        )
        .unwrap();
        assert_eq!(c.window_steps, 20);
        assert_eq!(c.position_scale_m, 25.5);
        let err = load::<road_data::WindowConfig>(None, &["window_step=20".into()]).unwrap_err();
        assert!(format!("{err:#}").contains("window_step"), "{err:#}");
        assert!(load::<road_data::WindowConfig>(None, &["nonsense".into()]).is_err());
    }
}
