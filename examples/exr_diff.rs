//! Compares two lightmaps texel by texel: how far a GPU bake is from the same bake on
//! lavapipe, or any bake from a reference (docs/performance.md, "GPU against lavapipe").
//!
//! How: reads the `R`, `G`, `B` channels of the first layer of both files (the full
//! lightmap, DESIGN §5), takes the texels where either file is non-zero (gutters and
//! unused texels are zero in both), and prints, for the luminance `0.2126 R + 0.7152 G +
//! 0.0722 B`, the RMS difference over the RMS of the second file (the metric of
//! docs/accuracy.md), the mean ratio first/second, and the largest absolute difference.
//!
//! Limits: no texel masks beyond "non-zero"; both files must have the same size.
//!
//! Usage: `cargo run --release --example exr_diff -- A.exr B.exr`

use std::process::ExitCode;

use exr::prelude::{ReadChannels, ReadLayers};

fn luminance(path: &str) -> Result<(usize, usize, Vec<f64>), String> {
    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_file(path)
        .map_err(|e| format!("{path}: {e}"))?;
    let layer = &image.layer_data;
    let channel = |name: &str| {
        layer
            .channel_data
            .list
            .iter()
            .find(|c| c.name.to_string() == name)
            .map(|c| c.sample_data.values_as_f32().map(f64::from).collect::<Vec<f64>>())
            .ok_or_else(|| format!("{path}: no channel {name}"))
    };
    let (r, g, b) = (channel("R")?, channel("G")?, channel("B")?);
    let lum = r
        .iter()
        .zip(&g)
        .zip(&b)
        .map(|((r, g), b)| 0.2126 * r + 0.7152 * g + 0.0722 * b)
        .collect();
    Ok((layer.size.0, layer.size.1, lum))
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [a, b] = args.as_slice() else {
        eprintln!("usage: exr_diff A.exr B.exr");
        return ExitCode::from(2);
    };
    let (la, lb) = match (luminance(a), luminance(b)) {
        (Ok(la), Ok(lb)) => (la, lb),
        (Err(e), _) | (_, Err(e)) => {
            eprintln!("exr_diff: {e}");
            return ExitCode::from(2);
        }
    };
    if (la.0, la.1) != (lb.0, lb.1) {
        eprintln!("exr_diff: sizes differ: {}x{} against {}x{}", la.0, la.1, lb.0, lb.1);
        return ExitCode::from(2);
    }
    let (mut n, mut diff2, mut ref2, mut sum_a, mut sum_b, mut worst) = (0usize, 0.0, 0.0, 0.0, 0.0, 0.0f64);
    for (&x, &y) in la.2.iter().zip(&lb.2) {
        if x == 0.0 && y == 0.0 {
            continue;
        }
        n += 1;
        diff2 += (x - y) * (x - y);
        ref2 += y * y;
        sum_a += x;
        sum_b += y;
        worst = worst.max((x - y).abs());
    }
    if n == 0 || ref2 == 0.0 {
        eprintln!("exr_diff: {b} is black");
        return ExitCode::from(2);
    }
    println!(
        "texels {n}  rms_rel {:.4e}  mean_ratio {:.6}  max_abs {:.4e}",
        (diff2 / ref2).sqrt(),
        sum_a / sum_b,
        worst
    );
    ExitCode::SUCCESS
}
