//! `hapcloud gpu-info`: opens the GPU context and reports the chosen adapter.

use hapcloud::gpu::GpuContext;

#[derive(clap::Args)]
pub struct Args {
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let ctx = GpuContext::new()?;
    let adapter = ctx.adapter();
    let period = ctx.timestamp_period_ns();
    if args.json {
        let out = serde_json::json!({
            "adapter": adapter.name,
            "device_type": adapter.device_type,
            "driver": adapter.driver,
            "timestamp_period_ns": period,
            "host_clock": ctx.host_clock(),
        });
        println!("{out}");
    } else {
        println!("adapter: {} ({})", adapter.name, adapter.device_type);
        println!("driver: {}", adapter.driver);
        match period {
            Some(p) => println!("timestamp queries: yes, {p} ns per tick"),
            None => println!("timestamp queries: not supported (no per-stage GPU times)"),
        }
        println!("GPU pass times: {}", ctx.host_clock());
    }
    Ok(())
}
