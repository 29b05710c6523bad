//! `cargo bench`: the forward model's speed table (the same as `biscale bench speed`).

fn main() {
    let reps = std::env::var("BISCALE_BENCH_REPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    match biscale::bench::speed(reps, &biscale::library::progress::Progress { quiet: true }) {
        Ok(table) => print!("{table}"),
        Err(e) => {
            eprintln!("bench: {e}");
            std::process::exit(2);
        }
    }
}
