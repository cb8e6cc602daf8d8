//! End-to-end pipeline throughput for 1, 2 and 4 flow workers, all stages as threads over
//! crossbeam, on a small synthetic scene (4 frames, 253×138, 15 coarse poses). One iteration is
//! one whole stream; criterion reports time per stream (frames/s = 4 / time). `asgreg bench
//! pipeline` runs the same at 505×275 with a printed table.

use std::time::Duration;

use asgreg::io::mesh_file::read_mesh;
use asgreg::runtime::config::PipelineConfig;
use asgreg::runtime::run_in_process;
use asgreg::stage::ingest::SourceConfig;
use asgreg::synth::{generate_scene, SynthConfig};
use asgreg::transport::crossbeam::CrossbeamTransport;
use criterion::{criterion_group, criterion_main, Criterion, Throughput};

const FRAMES: usize = 4;

fn pipeline_benches(c: &mut Criterion) {
    let dir = tempfile::tempdir().expect("temporary directory");
    let synth = SynthConfig {
        seed: 3,
        width_px: 253,
        height_px: 138,
        image_count: FRAMES,
        initial_levels_px: vec![15.0],
        supersampling: 1,
        ..SynthConfig::default()
    };
    generate_scene(&synth, dir.path()).expect("synthetic scene");
    let base = PipelineConfig {
        mesh: dir.path().join("model.ply"),
        source: SourceConfig::scene(dir.path(), 15),
        ..PipelineConfig::default()
    };
    let mesh = read_mesh(&base.mesh).expect("mesh");
    let mut group = c.benchmark_group("pipeline");
    group.sample_size(10);
    group.measurement_time(Duration::from_secs(20));
    group.throughput(Throughput::Elements(FRAMES as u64));
    for flow_workers in [1u32, 2, 4] {
        let mut config = base.clone();
        config.workers.flow = flow_workers;
        group.bench_function(format!("flow_workers_{flow_workers}"), |b| {
            b.iter(|| {
                config.transport.pipeline = format!("bench-{flow_workers}");
                let transport = CrossbeamTransport::new(config.transport.clone());
                let collected = run_in_process(
                    &config,
                    &transport,
                    &mesh,
                    Duration::from_secs(600),
                    &mut |_| {},
                )
                .expect("pipeline run");
                assert_eq!(collected.results.len(), FRAMES);
                collected
            })
        });
    }
    group.finish();
}

criterion_group!(benches, pipeline_benches);
criterion_main!(benches);
