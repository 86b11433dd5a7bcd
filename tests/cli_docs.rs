//! The manual holds together: every relative link and picture in `docs/` and `README.md`
//! resolves to a file (and a `#section` to a heading of it), no page is over 20 kB and all of
//! `docs/`'s markdown is under 100 kB.

use std::path::{Path, PathBuf};

fn pages() -> Vec<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut pages = vec![root.join("README.md")];
    for entry in std::fs::read_dir(root.join("docs")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "md") {
            pages.push(path);
        }
    }
    pages.sort();
    pages
}

/// The targets of `[text](target)` and `![alt](target)` links, outside code.
fn links(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut in_fence = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            in_fence = !in_fence;
            continue;
        }
        if in_fence {
            continue;
        }
        // Inline code spans may hold brackets that are not links.
        let plain: String = line.split('`').step_by(2).collect::<Vec<_>>().join("");
        let mut rest = plain.as_str();
        while let Some(i) = rest.find("](") {
            let after = &rest[i + 2..];
            let Some(end) = after.find(')') else { break };
            out.push(after[..end].to_string());
            rest = &after[end..];
        }
    }
    out
}

/// GitHub's anchor of a heading: lower case, spaces to `-`, punctuation dropped.
fn anchor(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c),
            _ => None,
        })
        .collect()
}

#[test]
fn every_relative_link_resolves() {
    let mut checked = 0;
    for page in pages() {
        let text = std::fs::read_to_string(&page).unwrap();
        for target in links(&text) {
            if target.contains("://") || target.starts_with("mailto:") {
                continue;
            }
            let (file, section) = match target.split_once('#') {
                Some((f, s)) => (f, Some(s)),
                None => (target.as_str(), None),
            };
            let path = if file.is_empty() {
                page.clone()
            } else {
                page.parent().unwrap().join(file)
            };
            assert!(
                path.exists(),
                "{}: link to {target} does not resolve",
                page.display()
            );
            if let Some(section) = section {
                let target_text = std::fs::read_to_string(&path).unwrap();
                let found = target_text
                    .lines()
                    .filter_map(|l| l.strip_prefix('#'))
                    .any(|h| anchor(h.trim_start_matches('#')) == section);
                assert!(found, "{}: no section #{section} in {file}", page.display());
            }
            checked += 1;
        }
    }
    assert!(checked > 50, "only {checked} links found");
}

#[test]
fn the_manual_stays_small() {
    let mut total = 0;
    for page in pages() {
        let size = std::fs::metadata(&page).unwrap().len();
        assert!(size <= 20_000, "{} is {size} bytes", page.display());
        if page.parent().unwrap().ends_with("docs") {
            total += size;
        }
    }
    assert!(total < 100_000, "docs/ holds {total} bytes of markdown");
}

#[test]
fn link_parser_finds_links_and_skips_code() {
    let text = "see [a](a.md) and ![p](p.png)\n`[x](not.md)`\n```\n[y](no.md)\n```\n";
    assert_eq!(links(text), ["a.md", "p.png"]);
    assert_eq!(
        anchor(" Jumps on `torso_approach_realistic`"),
        "jumps-on-torso_approach_realistic"
    );
}
