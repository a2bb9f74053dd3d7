//! `cargo bench -p amr-core --features kdtree-baseline`: the heading search (ours and the paper's
//! KD-tree baseline) and the whole pipeline without AMCL, at 2 × 271 and 2 × 655 points.
//! `amr bench vamr` prints the same stages as a table in the paper's Table 4 layout.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs, reason = "benchmark code")]

use std::hint::black_box;

use amr_core::config::{Configuration, VamrParams, parse_file};
use amr_core::vamr::heading::{
    AngleGrid, HeadingProblem, SearchScratch, TargetScan, kdtree_baseline, search,
};
use amr_core::vamr::pipeline::Pipeline;
use amr_core::vamr::preprocess::preprocess;
use amr_core::vamr::synthetic::Pair;
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};

fn params() -> VamrParams {
    parse_file("vamr.toml", include_str!("../../config/vamr.toml")).unwrap()
}

fn bench(c: &mut Criterion) {
    let params = params();
    let h = params.heading;
    for beams in [271usize, 655] {
        let pair = Pair::straight(beams).unwrap();
        let (site, scans, truth) = (&pair.site, &pair.scans, pair.truth());
        let pa = preprocess(&scans[0], &site.mount, &params.preprocess);
        let pb = preprocess(&scans[1], &site.mount, &params.preprocess);
        let target =
            TargetScan::new(&scans[0], &site.mount, &pa.smoothed_points).with_surface(h.surface_jump_m());
        let problem = HeadingProblem::new(&pb.smoothed_points, &target, [truth.x, truth.y], &h);
        let full = AngleGrid::full(h.step_deg.get());
        let refined = AngleGrid::around(truth.theta, h.refine_window_deg.get(), h.step_deg.get());
        let mut scratch = SearchScratch::default();
        let mut g = c.benchmark_group("heading");
        g.bench_with_input(BenchmarkId::new("full", beams), &beams, |b, _| {
            b.iter(|| search(black_box(&problem), &full, &mut scratch))
        });
        g.bench_with_input(BenchmarkId::new("refined", beams), &beams, |b, _| {
            b.iter(|| search(black_box(&problem), &refined, &mut scratch))
        });
        let target_pts: Vec<[f64; 2]> = pa.smoothed_points.iter().map(|b| b.p).collect();
        g.sample_size(10);
        g.bench_with_input(BenchmarkId::new("kdtree-baseline-full", beams), &beams, |b, _| {
            b.iter(|| {
                kdtree_baseline::search(
                    &pb.smoothed_points,
                    &target_pts,
                    problem.translation,
                    h.distance_gate_m.get(),
                    &full,
                )
            })
        });
        g.finish();

        let packets = pair.packets();
        let mut pipeline = Pipeline::new(2, params.clone(), Configuration::T4, 0.05, 0.1);
        pipeline.update(&packets).unwrap();
        c.bench_with_input(BenchmarkId::new("pipeline-t4-refined", beams), &beams, |b, _| {
            b.iter(|| pipeline.update(black_box(&packets)))
        });
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
