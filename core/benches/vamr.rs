//! `cargo bench -p amr-core --features kdtree-baseline`: the heading search (ours and the paper's
//! KD-tree baseline) and the whole pipeline without AMCL, at 2 × 271 and 2 × 655 points.
//! `amr bench vamr` times the same scene (`amr_core::vamr::synthetic::PairStages`) and prints its
//! stages as a table in the paper's Table 4 layout.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs, reason = "benchmark code")]

use std::hint::black_box;

use amr_core::config::{VamrParams, parse_file};
use amr_core::vamr::heading::{SearchScratch, kdtree_baseline, search};
use amr_core::vamr::synthetic::PairStages;
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};

fn params() -> VamrParams {
    parse_file("vamr.toml", include_str!("../../config/vamr.toml")).unwrap()
}

fn bench(c: &mut Criterion) {
    let params = params();
    let h = params.heading;
    for beams in [271usize, 655] {
        let stages = PairStages::new(beams, &params).unwrap();
        let problem = stages.problem(&h);
        let (full, refined) = (stages.full, stages.refined);
        let mut scratch = SearchScratch::default();
        let mut g = c.benchmark_group("heading");
        g.bench_with_input(BenchmarkId::new("full", beams), &beams, |b, _| {
            b.iter(|| search(black_box(&problem), &full, &mut scratch))
        });
        g.bench_with_input(BenchmarkId::new("refined", beams), &beams, |b, _| {
            b.iter(|| search(black_box(&problem), &refined, &mut scratch))
        });
        let target_pts = stages.target_points();
        let source = &stages.preprocessed[1].smoothed_points;
        g.sample_size(10);
        g.bench_with_input(BenchmarkId::new("kdtree-baseline-full", beams), &beams, |b, _| {
            b.iter(|| {
                kdtree_baseline::search(
                    source,
                    &target_pts,
                    problem.translation,
                    h.distance_gate_m.get(),
                    &full,
                )
            })
        });
        g.finish();

        let packets = stages.pair.packets();
        let mut pipeline = stages.primed_pipeline(&params).unwrap();
        c.bench_with_input(BenchmarkId::new("pipeline-t4-refined", beams), &beams, |b, _| {
            b.iter(|| pipeline.update(black_box(&packets)))
        });
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
