//! Worker tags and job requirements: the names pools are made of.
//!
//! A tag is short and plain so that it can be a Prometheus label value, a Kubernetes
//! label value and a shell word without quoting: the same name then reads the same in
//! `tessera workers`, in `/metrics` and in an autoscaler's query.

/// At most this many tags per worker, and requirements per job.
pub const MAX_TAGS: usize = 32;

/// At most this many bytes per tag.
pub const MAX_TAG_BYTES: usize = 64;

/// Checks one tag: 1 to 64 bytes of lowercase ASCII letters, digits, `.`, `_` and `-`,
/// starting with a letter or a digit. The error is one line naming the tag.
pub fn check_tag(tag: &str) -> Result<(), String> {
    let shown = || tag.escape_debug().to_string();
    if tag.is_empty() {
        return Err("a tag is empty: tags are 1 to 64 characters".into());
    }
    if tag.len() > MAX_TAG_BYTES {
        return Err(format!(
            "tag \"{}\" is {} bytes long: tags are at most {MAX_TAG_BYTES}",
            shown(),
            tag.len()
        ));
    }
    let first_ok = tag
        .bytes()
        .next()
        .is_some_and(|b| b.is_ascii_lowercase() || b.is_ascii_digit());
    let rest_ok = tag
        .bytes()
        .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b"._-".contains(&b));
    if !first_ok || !rest_ok {
        return Err(format!(
            "tag \"{}\" is not a tag name: lowercase letters, digits, '.', '_' and '-', \
             starting with a letter or a digit",
            shown()
        ));
    }
    Ok(())
}

/// Checks a worker's tags or a job's requirements (each with [`check_tag`], at most
/// [`MAX_TAGS`]) and returns them sorted, each once: the form pools are named by.
pub fn check_tags(tags: &[String]) -> Result<Vec<String>, String> {
    for tag in tags {
        check_tag(tag)?;
    }
    let mut sorted = tags.to_vec();
    sorted.sort();
    sorted.dedup();
    if sorted.len() > MAX_TAGS {
        return Err(format!(
            "{} tags: at most {MAX_TAGS} are allowed",
            sorted.len()
        ));
    }
    Ok(sorted)
}

/// The pool a job's tiles wait in: its requirements, sorted, joined with `,` (the
/// empty string for a job any worker may take).
pub fn pool_name(require: &[String]) -> String {
    let mut sorted = require.to_vec();
    sorted.sort();
    sorted.dedup();
    sorted.join(",")
}

/// Whether a worker with `tags` has every tag of `require`.
pub fn qualifies(tags: &[String], require: &[String]) -> bool {
    require.iter().all(|r| tags.contains(r))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tags_follow_the_grammar() {
        for good in ["gpu", "a", "0", "avx-512", "zone.eu_1", &"x".repeat(64)] {
            assert_eq!(check_tag(good), Ok(()), "{good}");
        }
        assert!(check_tag("").unwrap_err().contains("empty"));
        assert!(check_tag(&"x".repeat(65)).unwrap_err().contains("65 bytes"));
        for bad in ["GPU", "-gpu", ".x", "g p", "gpu\n", "é"] {
            let err = check_tag(bad).unwrap_err();
            assert!(err.contains(&bad.escape_debug().to_string()), "{err}");
            assert!(!err.contains('\n'), "{err}");
        }
    }

    #[test]
    fn tag_lists_are_sorted_once_and_bounded() {
        let tags: Vec<String> = ["ssd", "gpu", "ssd"].map(String::from).to_vec();
        assert_eq!(check_tags(&tags), Ok(vec!["gpu".into(), "ssd".into()]));
        let many: Vec<String> = (0..33).map(|i| format!("t{i}")).collect();
        assert!(check_tags(&many).unwrap_err().contains("at most 32"));
        assert!(check_tags(&many[..32]).is_ok());
        assert_eq!(pool_name(&tags), "gpu,ssd");
        assert_eq!(pool_name(&[]), "");
        assert!(qualifies(&tags, &["gpu".into()]));
        assert!(qualifies(&tags, &[]));
        assert!(!qualifies(&[], &["gpu".into()]));
    }
}
