//! Short names derived from user input, shared by sweeps (cell ids) and reports (titles,
//! file names).

use std::path::Path;

/// The last path component of a policy directory (`runs/kp/` -> `kp`), or the whole string
/// when it has none (`..`).
pub(crate) fn policy_label(policy: &str) -> &str {
    Path::new(policy)
        .file_name()
        .and_then(|s| s.to_str())
        .unwrap_or(policy)
}

/// A file-name-safe version of `s`: keeps `[A-Za-z0-9._-]`, maps the rest to `_`.
pub(crate) fn slug(s: &str) -> String {
    s.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_') {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// A cell id's or plot name's burst-phase part: `-ph<N>` for a nonzero phase, nothing at
/// phase 0 (the default).
pub(crate) fn phase_suffix(phase: usize) -> String {
    if phase == 0 {
        String::new()
    } else {
        format!("-ph{phase}")
    }
}

/// A cell id's or plot name's span part: `-span<N>` for a shortened span, nothing for the
/// full one.
pub(crate) fn span_suffix(span: Option<usize>) -> String {
    span.map_or(String::new(), |s| format!("-span{s}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels_and_slugs() {
        assert_eq!(
            policy_label("../assets/policies/pusht_keypoints_cpu"),
            "pusht_keypoints_cpu"
        );
        assert_eq!(policy_label("runs/kp/"), "kp");
        assert_eq!(policy_label(".."), "..");
        assert_eq!(policy_label("p"), "p");
        assert_eq!(slug("kp-blank burst/q=2"), "kp-blank_burst_q_2");
    }
}
