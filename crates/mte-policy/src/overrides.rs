//! Config fields replaced from a JSON object (`mte train ... --config FILE`), shared by every
//! policy class: a key the config does not have is an error naming it, never silently dropped.

use serde::Serialize;
use serde::de::DeserializeOwned;

use crate::error::{PolicyError, config_err};

fn json_err(source: serde_json::Error) -> PolicyError {
    PolicyError::Json {
        path: "<overrides>".into(),
        source,
    }
}

/// `base` with the top-level fields of `patch` (a JSON object, LeRobot's config.json names)
/// replaced. The caller validates the result.
pub fn apply<T: Serialize + DeserializeOwned>(
    base: &T,
    patch: &serde_json::Value,
) -> Result<T, PolicyError> {
    let Some(fields) = patch.as_object() else {
        return Err(config_err(
            "<overrides>",
            patch,
            "a JSON object of config fields",
        ));
    };
    let mut v = serde_json::to_value(base).map_err(json_err)?;
    let before: Vec<String> = v
        .as_object()
        .map(|o| o.keys().cloned().collect())
        .unwrap_or_default();
    let Some(obj) = v.as_object_mut() else {
        return Err(config_err("<config>", "not an object", "a JSON object"));
    };
    for (k, val) in fields {
        obj.insert(k.clone(), val.clone());
    }
    let out: T = serde_json::from_value(v).map_err(json_err)?;
    // A key serde ignored is absent before and after: a typo, not a field.
    let after = serde_json::to_value(&out).map_err(json_err)?;
    let known = |k: &String| before.contains(k) || after.get(k.as_str()).is_some();
    if let Some(k) = fields.keys().find(|k| !known(k)) {
        return Err(config_err(
            "<overrides>",
            k,
            "a field of this policy's config",
        ));
    }
    Ok(out)
}
