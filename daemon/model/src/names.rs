//! The one rule for the names of nodes and tiles. A node's name is also its certificate's DNS name
//! (`isowall keygen` writes `NAME.pem` and `NAME.key`, and TLS checks the name), so the config
//! accepts exactly the names keygen and TLS accept: 1 to [`MAX_NAME_LEN`] ASCII letters, digits,
//! '-' and '.', in dot-separated labels that are not empty and neither start nor end with '-',
//! the last label not all digits (TLS would read `10.0.0.1` as an address, not a name). Tiles
//! follow the same rule (their names become file names of snapshots).

/// The longest name: one DNS label.
pub const MAX_NAME_LEN: usize = 63;

/// What is wrong with `name` as a node or tile name, or `None` when it is a good one.
pub fn name_problem(name: &str) -> Option<String> {
    if name.is_empty() {
        return Some("is empty".into());
    }
    let shown: String = name.chars().take(MAX_NAME_LEN + 8).collect();
    let shown = if shown.len() < name.len() { format!("{shown}...") } else { shown };
    let chars = name.chars().count();
    if chars > MAX_NAME_LEN {
        return Some(format!(
            "'{shown}' has {chars} characters, more than {MAX_NAME_LEN} (it is a certificate's DNS name)"
        ));
    }
    let ok_char = |c: char| c.is_ascii_alphanumeric() || c == '-' || c == '.';
    let labels_ok = name.split('.').all(|l| !l.is_empty() && !l.starts_with('-') && !l.ends_with('-'));
    if !name.chars().all(ok_char) || !labels_ok {
        return Some(format!(
            "'{shown}' may hold only letters, digits, '-' and '.' (dot-separated parts, none empty, none \
             starting or ending with '-'): it is a certificate's DNS name"
        ));
    }
    if name.rsplit('.').next().is_some_and(|last| last.chars().all(|c| c.is_ascii_digit())) {
        return Some(format!("'{shown}' ends in a part of digits only: TLS would take it for an address"));
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn good_names_pass_and_bad_ones_say_why() {
        for good in ["node0", "n", "sva-node1.cluster", "Node-1", "t00", "a.b2", "0x", &"a".repeat(63)] {
            assert_eq!(name_problem(good), None, "{good}");
        }
        for (bad, why) in [
            ("", "is empty"),
            ("node_1", "may hold only"),
            ("a b", "may hold only"),
            ("../n1", "may hold only"),
            ("-x", "may hold only"),
            ("x-", "may hold only"),
            (".x", "may hold only"),
            ("a..b", "may hold only"),
            ("x.", "may hold only"),
            ("née", "may hold only"),
            ("7", "digits only"),
            ("10.0.0.1", "digits only"),
            ("node.7", "digits only"),
        ] {
            let p = name_problem(bad).unwrap_or_else(|| panic!("{bad:?} passed"));
            assert!(p.contains(why), "{bad:?}: {p}");
        }
        let long = "a".repeat(100);
        let p = name_problem(&long).unwrap();
        assert!(p.contains("100 characters, more than 63"), "{p}");
        assert!(p.len() < 200, "a long name is shown shortened: {p}");
    }
}
