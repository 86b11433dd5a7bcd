//! `hapcloud config`: the sections of a node config (`hapcloud run --config FILE`), or with
//! `--print [SECTION]` the complete default config as a commented TOML file to copy and edit.
//!
//! The values are the config types' `Default`s, serialized; the comments are the types' own
//! doc comments (read from `src/` by `build.rs`), so the file cannot drift from the code.

use anyhow::Context;
use hapcloud::node::NodeConfig;
use std::fmt::Write as _;

/// A deserializable type of the crate with its documentation.
pub struct TypeDoc {
    pub name: &'static str,
    pub doc: &'static str,
    /// The tag key of an internally tagged enum.
    pub tag: Option<&'static str>,
    pub fields: &'static [FieldDoc],
    /// An enum's variants (their names in a file) with their docs.
    pub variants: &'static [(&'static str, &'static str)],
}

/// A struct field: its key, the type inside `Option`/`Vec`, and its doc.
pub struct FieldDoc {
    pub name: &'static str,
    pub ty: &'static str,
    pub list: bool,
    pub flatten: bool,
    pub doc: &'static str,
}

include!(concat!(env!("OUT_DIR"), "/config_docs.rs"));

#[derive(clap::Args)]
pub struct Args {
    /// Print the default config (or only its SECTION, e.g. `frontend` or `surface.shells`)
    /// as a commented TOML file: every key with its doc, unit, range and default.
    #[arg(long, value_name = "SECTION", num_args = 0..=1, default_missing_value = "")]
    print: Option<String>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    match args.print.as_deref() {
        Some(section) => print!("{}", print(section)?),
        None => {
            let tables = root_entries()?.into_iter().filter_map(|(key, ty, doc)| {
                let ty = ty.filter(|t| !t.fields.is_empty())?;
                Some((key, if doc.is_empty() { ty.doc } else { doc }))
            });
            for (key, doc) in tables {
                println!("{key:<14} {}", first_sentence(doc));
            }
            println!("\n`hapcloud config --print [SECTION]` prints the defaults with their docs.");
        }
    }
    Ok(())
}

/// The root of a `--config` file: the node config's keys and the tables `hapcloud run` reads
/// beside it (`[mcap]`, and with the ros2 feature `[zenoh]`, `[zenoh_source]`, `[publish]`).
fn root_value() -> anyhow::Result<toml::Table> {
    let mut root = toml::Table::try_from(NodeConfig::default())?;
    root.insert(
        "mcap".into(),
        toml::Value::try_from(hapcloud::io::mcap::McapReaderConfig::default())?,
    );
    #[cfg(feature = "ros2")]
    {
        use hapcloud::io::zenoh as z;
        root.insert(
            "zenoh".into(),
            toml::Value::try_from(z::ZenohConfig::default())?,
        );
        root.insert(
            "zenoh_source".into(),
            toml::Value::try_from(z::ZenohSourceConfig::default())?,
        );
        root.insert(
            "publish".into(),
            toml::Value::try_from(z::ZenohPublisherConfig::default())?,
        );
    }
    Ok(root)
}

/// The types of the tables beside the node config's keys, by key.
const SIDE_TABLES: [(&str, &str); 4] = [
    ("mcap", "McapReaderConfig"),
    ("zenoh", "ZenohConfig"),
    ("zenoh_source", "ZenohSourceConfig"),
    ("publish", "ZenohPublisherConfig"),
];

/// The root's keys in the order they are printed, with their types and docs.
fn root_entries() -> anyhow::Result<Vec<(&'static str, Option<&'static TypeDoc>, &'static str)>> {
    let root = root_value()?;
    let node = find("NodeConfig", &root).context("no docs for NodeConfig")?;
    let mut entries: Vec<_> = fields(node)
        .into_iter()
        .map(|f| (f.name, find(f.ty, &table_of(&root, f.name)), f.doc))
        .collect();
    for (key, ty) in SIDE_TABLES {
        if root.contains_key(key) {
            let t = find(ty, &table_of(&root, key));
            entries.push((key, t, t.map_or("", |t| t.doc)));
        }
    }
    Ok(entries)
}

fn table_of(table: &toml::Table, key: &str) -> toml::Table {
    table
        .get(key)
        .and_then(toml::Value::as_table)
        .cloned()
        .unwrap_or_default()
}

/// The type named `name` whose keys cover `value`'s (names are not unique in the crate).
fn find(name: &str, value: &toml::Table) -> Option<&'static TypeDoc> {
    let mut candidates = TYPES.iter().filter(|t| t.name == name);
    let first = candidates.next()?;
    let covers = |t: &'static TypeDoc| {
        let keys: Vec<&str> = fields(t).iter().map(|f| f.name).collect();
        value.keys().all(|k| keys.contains(&k.as_str()))
    };
    if covers(first) {
        return Some(first);
    }
    candidates.find(|t| covers(t)).or(Some(first))
}

/// A struct's keys in declaration order, with `#[serde(flatten)]` fields expanded.
fn fields(t: &'static TypeDoc) -> Vec<&'static FieldDoc> {
    t.fields
        .iter()
        .flat_map(
            |f| match (f.flatten, TYPES.iter().find(|x| x.name == f.ty)) {
                (true, Some(inner)) => fields(inner),
                _ => vec![f],
            },
        )
        .collect()
}

/// The default config, or its table at the dotted path `section` (empty: all of it).
pub fn print(section: &str) -> anyhow::Result<String> {
    let root = root_value()?;
    let mut out = String::from(
        "# hapcloud node config (`hapcloud run --config FILE`): the defaults; a key left out\n\
         # keeps its default. Generated by `hapcloud config --print` from the config types.\n",
    );
    if section.is_empty() {
        let entries = root_entries()?;
        let node = find("NodeConfig", &root).context("no docs for NodeConfig")?;
        let mut p = Printer { out: &mut out };
        p.table(&[], Some(node), &root, &entries);
        return Ok(out);
    }
    let mut value = toml::Value::Table(root);
    let mut ty: Option<&'static TypeDoc> = None;
    let mut doc = "";
    let mut path = Vec::new();
    for key in section.split('.') {
        let table = value.as_table().cloned().unwrap_or_default();
        let entries = match path.is_empty() {
            true => root_entries()?,
            false => entries_of(ty, &table),
        };
        let Some(entry) = entries.iter().find(|e| e.0 == key) else {
            let names: Vec<&str> = entries
                .iter()
                .filter(|e| {
                    table.get(e.0).is_some_and(toml::Value::is_table)
                        || e.1.is_some_and(|t| !t.fields.is_empty())
                })
                .map(|e| e.0)
                .collect();
            anyhow::bail!(
                "no config section `{section}` (sections{}: {})",
                if path.is_empty() {
                    String::new()
                } else {
                    format!(" of {}", path.join("."))
                },
                names.join(", ")
            );
        };
        value = table
            .get(key)
            .cloned()
            .unwrap_or(toml::Value::Table(toml::Table::new()));
        if !value.is_table() {
            anyhow::bail!("`{section}` is a key, not a section");
        }
        ty = entry.1;
        doc = entry.2;
        path.push(key);
    }
    let table = value.as_table().cloned().unwrap_or_default();
    let mut p = Printer { out: &mut out };
    p.comment(doc);
    writeln!(p.out, "[{}]", path.join("."))?;
    let entries = entries_of(ty, &table);
    p.table(&path, ty, &table, &entries);
    Ok(out)
}

/// A table's keys: its type's fields in order, then keys the type does not name (a map's).
fn entries_of(
    ty: Option<&'static TypeDoc>,
    value: &toml::Table,
) -> Vec<(&'static str, Option<&'static TypeDoc>, &'static str)> {
    let mut entries: Vec<_> = ty
        .map(fields)
        .unwrap_or_default()
        .into_iter()
        .map(|f| (f.name, find(f.ty, &table_of(value, f.name)), f.doc))
        .collect();
    for key in value.keys() {
        if !entries.iter().any(|e| e.0 == key) {
            // Leaked once per printed key outside the types (a map's keys): a short-lived CLI.
            entries.push((Box::leak(key.clone().into_boxed_str()), None, ""));
        }
    }
    entries
}

struct Printer<'a> {
    out: &'a mut String,
}

impl Printer<'_> {
    /// `doc` as `# ` lines of at most 96 characters.
    fn comment(&mut self, doc: &str) {
        let mut line = String::new();
        for word in doc.split_whitespace() {
            if !line.is_empty() && line.len() + word.len() + 1 > 94 {
                let _ = writeln!(self.out, "# {line}");
                line.clear();
            }
            if !line.is_empty() {
                line.push(' ');
            }
            line.push_str(word);
        }
        if !line.is_empty() {
            let _ = writeln!(self.out, "# {line}");
        }
    }

    /// The doc of a key whose type is `ty`: its own doc (else its type's), and an enum's
    /// choices.
    fn key_doc(&mut self, doc: &str, ty: Option<&TypeDoc>) {
        self.comment(if doc.is_empty() {
            ty.map_or("", |t| t.doc)
        } else {
            doc
        });
        if let Some(t) = ty.filter(|t| !t.variants.is_empty() && t.tag.is_none()) {
            let choices: Vec<String> = t
                .variants
                .iter()
                .map(|(name, doc)| match first_sentence(doc) {
                    "" => format!("\"{name}\""),
                    d => format!("\"{name}\" ({d})"),
                })
                .collect();
            self.comment(&format!("One of: {}.", choices.join("; ")));
        }
    }

    /// The keys of one table (`path`; its header already printed): plain values first, as
    /// TOML wants, then the sub-tables. A key without a value (an unset `Option`) is printed
    /// commented out.
    fn table(
        &mut self,
        path: &[&str],
        ty: Option<&'static TypeDoc>,
        value: &toml::Table,
        entries: &[(&'static str, Option<&'static TypeDoc>, &'static str)],
    ) {
        let field = |key: &str| ty.and_then(|t| fields(t).into_iter().find(|f| f.name == key));
        let is_table = |key: &str, t: Option<&TypeDoc>| match value.get(key) {
            Some(toml::Value::Table(_)) => true,
            Some(toml::Value::Array(a)) => {
                a.first().is_some_and(toml::Value::is_table)
                    || (a.is_empty() && t.is_some_and(|t| !t.fields.is_empty()))
            }
            Some(_) => false,
            None => t.is_some_and(|t| !t.fields.is_empty()),
        };
        for &(key, t, doc) in entries.iter().filter(|e| !is_table(e.0, e.1)) {
            self.out.push('\n');
            self.key_doc(doc, t);
            match value.get(key) {
                Some(v) => {
                    let _ = writeln!(self.out, "{key} = {}", value_text(v));
                }
                None => {
                    let ty = field(key).map_or("value", |f| f.ty);
                    let _ = writeln!(self.out, "# {key} = <{ty}> (optional; unset)");
                }
            }
        }
        for &(key, t, doc) in entries.iter().filter(|e| is_table(e.0, e.1)) {
            let mut sub: Vec<&str> = path.to_vec();
            sub.push(key);
            let header = sub.join(".");
            match value.get(key) {
                Some(toml::Value::Table(inner)) => {
                    self.out.push('\n');
                    self.key_doc(doc, t);
                    let _ = writeln!(self.out, "[{header}]");
                    self.table(&sub, t, inner, &entries_of(t, inner));
                }
                Some(toml::Value::Array(items)) if !items.is_empty() => {
                    for item in items {
                        let inner = item.as_table().cloned().unwrap_or_default();
                        self.out.push('\n');
                        self.key_doc(doc, t);
                        let _ = writeln!(self.out, "[[{header}]]");
                        self.table(&sub, t, &inner, &entries_of(t, &inner));
                    }
                }
                _ => {
                    // No default entry (an empty list, an unset table): its keys as comments.
                    let list = field(key).is_some_and(|f| f.list);
                    self.out.push('\n');
                    self.key_doc(doc, t);
                    let (open, close) = if list { ("[[", "]]") } else { ("[", "]") };
                    let _ = writeln!(self.out, "# {open}{header}{close} (none by default)");
                    if let Some(t) = t {
                        self.unset_keys(t);
                    }
                }
            }
        }
    }

    /// The keys of a table that has no default, commented out, with their docs.
    fn unset_keys(&mut self, t: &'static TypeDoc) {
        for f in fields(t) {
            let inner = TYPES.iter().find(|x| x.name == f.ty);
            self.key_doc(f.doc, inner);
            let _ = writeln!(self.out, "# {} = <{}>", f.name, f.ty);
        }
    }
}

/// A value as TOML; a float that is an `f32` is written in the shortest form that reads back
/// as the same `f32` (`0.02`, not `0.019999999552965164`).
fn value_text(v: &toml::Value) -> String {
    match v {
        toml::Value::Float(f) if f.is_finite() && f64::from(*f as f32) == *f => {
            let text = (*f as f32).to_string();
            if text.contains(['.', 'e']) {
                text
            } else {
                format!("{text}.0")
            }
        }
        toml::Value::Array(items) => {
            let items: Vec<String> = items.iter().map(value_text).collect();
            format!("[{}]", items.join(", "))
        }
        _ => v.to_string(),
    }
}

fn first_sentence(doc: &str) -> &str {
    match doc.find(". ") {
        Some(i) => &doc[..=i],
        None => doc,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What `print("")` prints, loaded as `hapcloud run --config` loads it: every section
    /// equals its default.
    #[test]
    fn printed_config_loads_as_the_defaults() {
        let text = print("").unwrap();
        let dir = std::env::temp_dir().join(format!("hapcloud-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("node.toml");
        std::fs::write(&path, &text).unwrap();
        let loaded = super::super::run::read_config(&path).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        assert_eq!(toml_of(&loaded.node), toml_of(&NodeConfig::default()));
        assert_eq!(
            toml_of(&loaded.mcap),
            toml_of(&hapcloud::io::mcap::McapReaderConfig::default())
        );
        #[cfg(feature = "ros2")]
        {
            use hapcloud::io::zenoh as z;
            assert_eq!(toml_of(&loaded.zenoh), toml_of(&z::ZenohConfig::default()));
            assert_eq!(
                toml_of(&loaded.zenoh_source),
                toml_of(&z::ZenohSourceConfig::default())
            );
            assert_eq!(
                toml_of(&loaded.publish),
                toml_of(&z::ZenohPublisherConfig::default())
            );
        }
        // The file has the defaults' keys, no more, no fewer (an empty list may be absent).
        let parsed: toml::Table = toml::from_str(&text).unwrap();
        assert_eq!(keys(&parsed, ""), keys(&root_value().unwrap(), ""));
    }

    /// Every field of every type reachable from the root is in the file: set, or commented
    /// out when it has no default value.
    #[test]
    fn every_key_is_printed() {
        let text = print("").unwrap();
        let lines: Vec<&str> = text.lines().collect();
        let mut seen = std::collections::HashSet::new();
        let mut stack: Vec<&'static TypeDoc> =
            vec![TYPES.iter().find(|t| t.name == "NodeConfig").unwrap()];
        for (_, ty) in SIDE_TABLES {
            #[cfg(not(feature = "ros2"))]
            if ty != "McapReaderConfig" {
                continue;
            }
            stack.push(TYPES.iter().find(|t| t.name == ty).unwrap());
        }
        let mut checked = 0;
        while let Some(t) = stack.pop() {
            if !seen.insert(t as *const TypeDoc) {
                continue;
            }
            for f in fields(t) {
                let key = f.name;
                let present = lines.iter().any(|l| {
                    let l = l.trim_start_matches("# ");
                    l.starts_with(&format!("{key} = "))
                        || l.starts_with('[')
                            && l.trim_matches(['[', ']', ' ']).rsplit('.').next() == Some(key)
                        || l.contains(&format!(".{key}]"))
                });
                assert!(present, "{}.{key} is not printed", t.name);
                checked += 1;
                stack.extend(
                    TYPES
                        .iter()
                        .filter(|x| x.name == f.ty && !x.fields.is_empty()),
                );
            }
        }
        assert!(checked > 100, "only {checked} keys checked");
    }

    #[test]
    fn a_section_prints_alone_and_a_wrong_one_names_the_choices() {
        let text = print("surface").unwrap();
        let parsed: toml::Table = toml::from_str(&text).unwrap();
        assert_eq!(parsed.keys().collect::<Vec<_>>(), ["surface"]);
        assert_eq!(
            parsed["surface"],
            toml::Value::try_from(NodeConfig::default().surface).unwrap()
        );
        let err = print("nonsense").unwrap_err().to_string();
        assert!(err.contains("frontend") && err.contains("surface"), "{err}");
        assert!(print("tick_rate_hz").is_err());
    }

    /// The dotted paths of all keys of `table`.
    fn keys(table: &toml::Table, prefix: &str) -> Vec<String> {
        let mut out = Vec::new();
        for (k, v) in table {
            let path = format!("{prefix}{k}");
            match v {
                toml::Value::Table(t) => out.extend(keys(t, &format!("{path}."))),
                // An empty list is the same as none: it is printed as a commented example.
                toml::Value::Array(a) if a.is_empty() => {}
                toml::Value::Array(a) if a.iter().all(toml::Value::is_table) => {
                    for t in a.iter().filter_map(toml::Value::as_table) {
                        out.extend(keys(t, &format!("{path}[].")));
                    }
                }
                _ => out.push(path),
            }
        }
        out.sort();
        out
    }

    fn toml_of<T: serde::Serialize>(v: &T) -> toml::Value {
        toml::Value::try_from(v).unwrap()
    }
}
