//! `hapcloud scenes`: lists the built-in scenes (name, description, bodies, cameras, effects)
//! or prints one as a complete scene file (`--print NAME`) to copy and edit.

use anyhow::Context;
use hapcloud::scene::{Scene, builtin};

#[derive(clap::Args)]
pub struct Args {
    /// Print this built-in scene's full TOML instead of the list.
    #[arg(long, value_name = "NAME")]
    print: Option<String>,
    /// One JSON object on stdout.
    #[arg(long)]
    json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if let Some(name) = args.print {
        let text = builtin::text(&name).with_context(|| {
            format!(
                "no built-in scene `{name}` (built-in scenes: {})",
                builtin::names().join(", ")
            )
        })?;
        print!("{text}");
        return Ok(());
    }
    let mut rows = Vec::new();
    for name in builtin::names() {
        let scene = Scene::from_builtin(&name)?;
        let f = &scene.file;
        rows.push(serde_json::json!({
            "name": name,
            "description": f.description,
            "duration_s": f.duration_s,
            "bodies": f.bodies.iter().map(|b| b.name.clone()).collect::<Vec<_>>(),
            "cameras": f.cameras.iter().map(|c| format!("{} {}Hz", c.name, c.rate_hz)).collect::<Vec<_>>(),
            "effects": f.effects.iter().map(|e| e.name()).collect::<Vec<_>>(),
        }));
    }
    if args.json {
        println!("{}", serde_json::json!({ "scenes": rows }));
        return Ok(());
    }
    for row in &rows {
        let effects = row["effects"].as_array().map_or(0, Vec::len);
        println!(
            "{:<28} {:>5.1} s  {} cameras  {:>2} effects  {}",
            row["name"].as_str().unwrap_or_default(),
            row["duration_s"].as_f64().unwrap_or_default(),
            row["cameras"].as_array().map_or(0, Vec::len),
            effects,
            row["description"].as_str().unwrap_or_default(),
        );
    }
    Ok(())
}
