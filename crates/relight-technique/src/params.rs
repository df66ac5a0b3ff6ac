//! `--set key=value` parameters, parsed into a technique's own `Params`
//! struct through serde with unknown keys refused, so a typo is an error
//! rather than a silent default.

use serde::de::DeserializeOwned;

#[derive(Debug, thiserror::Error)]
#[error("parameter error for technique '{technique}': {message}")]
pub struct ParamError {
    pub technique: &'static str,
    pub message: String,
}

/// Parses `key=value` pairs (values in TOML syntax: numbers, booleans,
/// quoted strings; a bare word is taken as a string) over `defaults`.
pub fn parse_params<T: DeserializeOwned + serde::Serialize>(
    technique: &'static str,
    defaults: &T,
    pairs: &[(String, String)],
) -> Result<T, ParamError> {
    let error = |message: String| ParamError { technique, message };
    let mut table = toml::Table::try_from(defaults).map_err(|e| error(e.to_string()))?;
    for (key, raw) in pairs {
        if !table.contains_key(key) {
            let known: Vec<&str> = table.keys().map(String::as_str).collect();
            return Err(error(format!(
                "unknown key '{key}'; known keys: {}",
                known.join(", ")
            )));
        }
        let value = toml::from_str::<toml::Table>(&format!("value = {raw}"))
            .ok()
            .and_then(|mut parsed| parsed.remove("value"))
            .unwrap_or_else(|| toml::Value::String(raw.clone()));
        table.insert(key.clone(), value);
    }
    T::deserialize(toml::Value::Table(table)).map_err(|e| error(format!("{e}")))
}

/// The scene file's `[technique]` table as `key=value` pairs followed by
/// `pairs`, so that the command line wins over the scene's defaults.
pub fn with_scene_section(
    scene: &relight_scene::Scene,
    technique: &str,
    pairs: &[(String, String)],
) -> Vec<(String, String)> {
    let mut merged = Vec::new();
    if let Some(toml::Value::Table(table)) = scene.technique_sections.get(technique) {
        for (key, value) in table {
            merged.push((key.clone(), value.to_string()));
        }
    }
    merged.extend_from_slice(pairs);
    merged
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::{Deserialize, Serialize};

    #[derive(Serialize, Deserialize, Debug, PartialEq)]
    #[serde(deny_unknown_fields)]
    struct Example {
        samples: u32,
        clamp: f32,
        mode: String,
    }

    #[test]
    fn values_override_defaults_and_typos_fail() {
        let defaults = Example {
            samples: 4,
            clamp: 1.0,
            mode: "fast".into(),
        };
        let parsed = parse_params(
            "x",
            &defaults,
            &[
                ("samples".into(), "16".into()),
                ("mode".into(), "slow".into()),
            ],
        )
        .unwrap();
        assert_eq!(
            parsed,
            Example {
                samples: 16,
                clamp: 1.0,
                mode: "slow".into()
            }
        );
        let typo = parse_params("x", &defaults, &[("sampels".into(), "16".into())]).unwrap_err();
        assert!(typo.to_string().contains("sampels") && typo.to_string().contains("samples"));
        let wrong_type = parse_params("x", &defaults, &[("samples".into(), "many".into())]);
        assert!(wrong_type.is_err());
    }
}
