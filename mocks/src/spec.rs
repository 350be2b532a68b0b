//! The `key=value,key=value` specs that the simulated bases take on the command line
//! (`--faults`, `--odometry-error`).

/// The items of `spec`, each split at its first `=` into a trimmed key and value (`None` for an
/// item without `=`); empty items (a trailing comma) are skipped.
pub fn items(spec: &str) -> impl Iterator<Item = (&str, Option<&str>)> {
    spec.split(',').map(str::trim).filter(|i| !i.is_empty()).map(|item| match item.split_once('=') {
        Some((k, v)) => (k.trim(), Some(v.trim())),
        None => (item, None),
    })
}

#[cfg(test)]
mod tests {
    #[test]
    fn items_split_at_the_first_equals_sign_and_skip_empty_ones() {
        let got: Vec<_> = super::items(" drop=0.1, delay = 0.2:30ms,,bare ,").collect();
        assert_eq!(got, [("drop", Some("0.1")), ("delay", Some("0.2:30ms")), ("bare", None)]);
    }
}
