//! Benchmarks of dense matching (dense SIFT and SIFT flow, Liu, Yuen, Torralba, TPAMI 2011)
//! on the real pairs: 505×275 from `tests/data/flow-pairs` (always there) and 1010×550 from the
//! shared data set (`../shared/data/flow-pairs`; the report says when it is absent and not measured):
//! per pair at 505×275 and 1010×550 on one and two threads, a frame's worth of flows (30 pairs),
//! and side-by-side comparisons of each optimisation against the straightforward code.
//!
//! `FLOW_BENCH_QUICK=1 cargo bench --bench flow` prints one-shot timings, end-point errors and the
//! side-by-side figures without criterion's repetitions (a few minutes on 2 cores).
//!
//! `FLOW_BENCH_STAGES=1 cargo bench --bench flow` times one one-way flow of the fast preset per
//! stage on one thread (dense SIFT of both images, pyramids, data cost, belief propagation): the
//! first run with fresh buffers (as a process that flows once pays, page faults included) and the
//! minimum of `FLOW_BENCH_REPEATS` (default 15) runs with reused buffers, in process CPU time
//! (dense SIFT, whole flow) and wall time (the flow's own per-stage timings); with the EPE.
//! `FLOW_BENCH_CONFIG='{"iterations": 8}'` replaces fields of the preset; `FLOW_BENCH_FRESH=1`
//! gives every rerun fresh flow buffers (as a new workspace per view pays);
//! `FLOW_BENCH_SIFT_THEN_PYRAMID=1` builds each image's pyramid right after its dense SIFT (as a
//! frame does) and flows on the given pyramids, the pyramids' time then counted with dense SIFT.

use std::hint::black_box;
use std::path::Path;
use std::time::{Duration, Instant};

use asgreg::core::dense_sift::{
    compute_dense_sift, DenseSiftConfig, DenseSiftImage, DenseSiftWorkspace,
};
use asgreg::core::flow_consistency::{
    match_query_to_renderings, match_sift_images, MatchConfig, MatchWorkspace, PixelMatches,
};
use asgreg::core::image::{Image, ImageView};
use asgreg::core::sift_flow::{
    compute_sift_flow, compute_sift_flow_on_pyramids, descriptor_l1_distance, FlowField, L1Kernel,
    SiftFlowConfig, SiftFlowWorkspace, SiftPyramid, SubpixelRefinement,
};
use criterion::{BenchmarkId, Criterion};
use rayon::prelude::*;

struct Pair {
    name: &'static str,
    first: Image<f32>,
    second: Image<f32>,
    truth: FlowField,
}

fn load_grey(path: &Path) -> Option<Image<f32>> {
    let image = image::open(path).ok()?.to_luma8();
    let (width, height) = image.dimensions();
    Image::new(
        width as usize,
        height as usize,
        image
            .pixels()
            .map(|pixel| pixel.0[0] as f32 / 255.0)
            .collect(),
    )
    .ok()
}

fn load_pair((name, folder): (&'static str, &str)) -> Option<Pair> {
    let directory = Path::new(env!("CARGO_MANIFEST_DIR")).join(folder);
    let Some(first) = load_grey(&directory.join(format!("{name}_im1.png"))) else {
        eprintln!(
            "pair {name} not measured: it is not in {}",
            directory.display()
        );
        return None;
    };
    let second = load_grey(&directory.join(format!("{name}_im2.png")))?;
    let truth = asgreg::io::flo::read_flo(&directory.join(format!("{name}_gt.flo"))).ok()?;
    Some(Pair {
        name,
        first,
        second,
        truth,
    })
}

fn sift(image: ImageView<'_, f32>) -> DenseSiftImage {
    let mut out = DenseSiftImage::default();
    compute_dense_sift(
        image,
        &DenseSiftConfig::default(),
        &mut DenseSiftWorkspace::default(),
        &mut out,
    )
    .expect("dense SIFT");
    out
}

fn flow(
    first: &DenseSiftImage,
    second: &DenseSiftImage,
    config: &SiftFlowConfig,
    workspace: &mut SiftFlowWorkspace,
) -> FlowField {
    let mut field = FlowField::default();
    let mut cost = Image::default();
    compute_sift_flow(
        first, None, second, None, config, workspace, &mut field, &mut cost,
    )
    .expect("SIFT flow");
    field
}

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool")
}

/// EPE and fraction under 1 px over pixels at least 20 px from the border.
fn score(field: &FlowField, truth: &FlowField) -> (f64, f64) {
    let (mut sum, mut under, mut count) = (0.0, 0usize, 0usize);
    let (u, v) = (field.u_px().data(), field.v_px().data());
    let (true_u, true_v) = (truth.u_px().data(), truth.v_px().data());
    for y in 20..field.height_px() - 20 {
        for x in 20..field.width_px() - 20 {
            let pixel = y * field.width_px() + x;
            let error =
                ((u[pixel] - true_u[pixel]) as f64).hypot((v[pixel] - true_v[pixel]) as f64);
            sum += error;
            under += (error < 1.0) as usize;
            count += 1;
        }
    }
    (sum / count as f64, under as f64 / count as f64)
}

/// CPU time of this process (user + system), from `/proc/self/stat`; `None` elsewhere. On a shared
/// machine it is steadier than wall time for single-threaded runs.
fn process_cpu_time() -> Option<Duration> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let after_name = stat.rsplit_once(')')?.1;
    let fields: Vec<&str> = after_name.split_whitespace().collect();
    let user: u64 = fields.get(11)?.parse().ok()?;
    let system: u64 = fields.get(12)?.parse().ok()?;
    Some(Duration::from_millis((user + system) * 10))
}

/// High-resolution CPU time of this process (`CLOCK_PROCESS_CPUTIME_ID`), Linux only.
fn precise_process_cpu_time() -> Duration {
    #[repr(C)]
    struct Timespec {
        seconds: i64,
        nanoseconds: i64,
    }
    extern "C" {
        fn clock_gettime(clock: i32, time: *mut Timespec) -> i32;
    }
    const CLOCK_PROCESS_CPUTIME_ID: i32 = 2;
    let mut time = Timespec {
        seconds: 0,
        nanoseconds: 0,
    };
    // SAFETY: `time` is a valid, writable timespec; the call only writes it.
    let status = unsafe { clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &mut time) };
    assert_eq!(status, 0, "clock_gettime");
    Duration::new(time.seconds as u64, time.nanoseconds as u32)
}

/// Per-stage times of one one-way flow (fast preset, one thread), see the module comment.
fn stages_report(pairs: &[Pair]) {
    let repeats: usize = std::env::var("FLOW_BENCH_REPEATS")
        .ok()
        .and_then(|value| value.parse().ok())
        .unwrap_or(15);
    // `FLOW_BENCH_CONFIG='{"iterations": 8}'`: fields that replace the fast preset's.
    let config = match std::env::var("FLOW_BENCH_CONFIG") {
        Ok(json) => {
            let mut value = serde_json::to_value(SiftFlowConfig::fast()).expect("config");
            let changes: serde_json::Value =
                serde_json::from_str(&json).expect("FLOW_BENCH_CONFIG");
            for (key, field) in changes.as_object().expect("a JSON object") {
                value[key] = field.clone();
            }
            serde_json::from_value(value).expect("FLOW_BENCH_CONFIG fields")
        }
        Err(_) => SiftFlowConfig::fast(),
    };
    let ms = |duration: Duration| duration.as_secs_f64() * 1e3;
    let fresh = std::env::var_os("FLOW_BENCH_FRESH").is_some();
    let sift_then_pyramid = std::env::var_os("FLOW_BENCH_SIFT_THEN_PYRAMID").is_some();
    pool(1).install(|| {
        for pair in pairs {
            let mut sift_workspace = DenseSiftWorkspace::default();
            let (mut first, mut second) = (DenseSiftImage::default(), DenseSiftImage::default());
            let (mut first_pyramid, mut second_pyramid) =
                (SiftPyramid::default(), SiftPyramid::default());
            let mut workspace = SiftFlowWorkspace::default();
            let mut field = FlowField::default();
            let mut cost = Image::default();
            // [sift, flow cpu, total cpu, pyramid, data cost, bp (wall)] of each run.
            let mut runs: Vec<[Duration; 6]> = Vec::new();
            for _ in 0..=repeats {
                if fresh {
                    workspace = SiftFlowWorkspace::default();
                }
                let started = precise_process_cpu_time();
                for (image, out, pyramid) in [
                    (&pair.first, &mut first, &mut first_pyramid),
                    (&pair.second, &mut second, &mut second_pyramid),
                ] {
                    compute_dense_sift(
                        image.view(),
                        &DenseSiftConfig::default(),
                        &mut sift_workspace,
                        out,
                    )
                    .expect("dense SIFT");
                    // `FLOW_BENCH_SIFT_THEN_PYRAMID=1`: each image's pyramid right after its
                    // dense SIFT (as a frame builds the query's and each rendering's), then the
                    // flow on the pyramids; the pyramids' CPU time is then in the first column.
                    if sift_then_pyramid {
                        pyramid.build(out, &config).expect("pyramid");
                    }
                }
                let sift_done = precise_process_cpu_time();
                let timings = if sift_then_pyramid {
                    compute_sift_flow_on_pyramids(
                        (&first, &first_pyramid, None),
                        (&second, &second_pyramid, None),
                        &config,
                        &mut workspace,
                        &mut field,
                        &mut cost,
                    )
                } else {
                    compute_sift_flow(
                        &first,
                        None,
                        &second,
                        None,
                        &config,
                        &mut workspace,
                        &mut field,
                        &mut cost,
                    )
                };
                let timings = timings.expect("SIFT flow");
                let done = precise_process_cpu_time();
                runs.push([
                    sift_done - started,
                    done - sift_done,
                    done - started,
                    timings.pyramid,
                    timings.data_cost,
                    timings.belief_propagation,
                ]);
            }
            let (epe, under_one) = score(&field, &pair.truth);
            let first_column = match sift_then_pyramid {
                true => "dense SIFT + pyramid x2",
                false => "dense SIFT x2",
            };
            let cold = runs[0];
            let warm: [Duration; 6] = std::array::from_fn(|stage| {
                runs[1..]
                    .iter()
                    .map(|run| run[stage])
                    .min()
                    .unwrap_or_default()
            });
            for (label, run) in [("first run", cold), ("min of reruns", warm)] {
                println!(
                    "{} one-way flow, fast preset, 1 thread, {label}: CPU {:.1} ms ({first_column} {:.1}, flow {:.1}); wall pyramid {:.1}, data cost {:.1}, BP {:.1} ms; EPE {epe:.4} px, < 1 px {under_one:.4}",
                    pair.name,
                    ms(run[2]),
                    ms(run[0]),
                    ms(run[1]),
                    ms(run[3]),
                    ms(run[4]),
                    ms(run[5]),
                );
            }
        }
    });
}

fn cpu_time<T>(mut run: impl FnMut() -> T) -> (Duration, T) {
    let before = process_cpu_time().unwrap_or_default();
    let value = run();
    (
        process_cpu_time()
            .unwrap_or_default()
            .saturating_sub(before),
        value,
    )
}

fn time<T>(mut run: impl FnMut() -> T) -> (Duration, T) {
    let started = Instant::now();
    let value = run();
    (started.elapsed(), value)
}

fn quick_report(pairs: &[Pair]) {
    let presets = [
        ("default", SiftFlowConfig::default()),
        ("fast", SiftFlowConfig::fast()),
    ];
    for pair in pairs {
        for threads in [1, 2] {
            pool(threads).install(|| {
                let mut workspace = DenseSiftWorkspace::default();
                let mut out = DenseSiftImage::default();
                let run = |workspace: &mut DenseSiftWorkspace, out: &mut DenseSiftImage| {
                    compute_dense_sift(
                        pair.first.view(),
                        &DenseSiftConfig::default(),
                        workspace,
                        out,
                    )
                    .expect("dense SIFT")
                };
                run(&mut workspace, &mut out);
                let (cpu, (wall, ())) = cpu_time(|| time(|| run(&mut workspace, &mut out)));
                println!(
                    "{} dense SIFT, {threads} thread(s): {:.1} ms wall, {:.0} ms CPU",
                    pair.name,
                    wall.as_secs_f64() * 1000.0,
                    cpu.as_secs_f64() * 1000.0
                );
            });
        }
        let first = sift(pair.first.view());
        let second = sift(pair.second.view());
        for (preset, config) in &presets {
            for threads in [1, 2] {
                pool(threads).install(|| {
                    let mut workspace = SiftFlowWorkspace::default();
                    let _warm = flow(&first, &second, config, &mut workspace);
                    let (cpu, (wall, field)) = cpu_time(|| time(|| flow(&first, &second, config, &mut workspace)));
                    let (epe, under_one) = score(&field, &pair.truth);
                    println!(
                        "{} SIFT flow {preset}, {threads} thread(s): {:.1} ms wall, {:.0} ms CPU, EPE {epe:.3} px, < 1 px {under_one:.3}",
                        pair.name,
                        wall.as_secs_f64() * 1000.0,
                        cpu.as_secs_f64() * 1000.0
                    );
                });
            }
        }
        // Side by side, one thread, same run: each speed optimisation against the straightforward
        // code (CPU time; results are identical within each group).
        pool(1).install(|| {
            let mut workspace = SiftFlowWorkspace::default();
            for (label, config) in [
                (
                    "straightforward: generic BP sweep, portable L1",
                    SiftFlowConfig {
                        specialised_kernels: false,
                        l1_kernel: L1Kernel::Portable,
                        ..Default::default()
                    },
                ),
                (
                    "fixed-size BP sweep, portable L1",
                    SiftFlowConfig {
                        l1_kernel: L1Kernel::Portable,
                        ..Default::default()
                    },
                ),
                (
                    "fixed-size BP sweep, SSE2 L1",
                    SiftFlowConfig {
                        l1_kernel: L1Kernel::Sse2,
                        ..Default::default()
                    },
                ),
                (
                    "fixed-size BP sweep, AVX2 L1 (default)",
                    SiftFlowConfig::default(),
                ),
                (
                    "without multigrid (30/60 iterations)",
                    SiftFlowConfig {
                        multigrid: false,
                        ..Default::default()
                    },
                ),
                (
                    "fast preset (multigrid, 4/20/4 iterations)",
                    SiftFlowConfig::fast(),
                ),
                (
                    "integer flow (no sub-pixel refinement)",
                    SiftFlowConfig {
                        subpixel: SubpixelRefinement::None,
                        ..Default::default()
                    },
                ),
                (
                    "belief-parabola sub-pixel refinement",
                    SiftFlowConfig {
                        subpixel: SubpixelRefinement::BeliefParabola,
                        ..Default::default()
                    },
                ),
            ] {
                let (cpu, field) = cpu_time(|| flow(&first, &second, &config, &mut workspace));
                let (epe, under_one) = score(&field, &pair.truth);
                println!(
                    "{} side by side, {label}: {:.0} ms CPU, EPE {epe:.3}, < 1 px {under_one:.3}",
                    pair.name,
                    cpu.as_secs_f64() * 1000.0
                );
            }
        });
        // A pair both ways: two independent flows (four pyramids, one after the other) against the
        // pair API (two pyramids, both directions side by side), fast preset.
        for threads in [1, 2] {
            let config = MatchConfig {
                sift_flow: SiftFlowConfig::fast(),
                ..Default::default()
            };
            pool(threads).install(|| {
                let mut workspace = SiftFlowWorkspace::default();
                let (separate_cpu, (separate_wall, _)) = cpu_time(|| {
                    time(|| {
                        let forward = flow(&first, &second, &config.sift_flow, &mut workspace);
                        let backward = flow(&second, &first, &config.sift_flow, &mut workspace);
                        (forward, backward)
                    })
                });
                let mut pair_workspace = MatchWorkspace::default();
                let mut out = PixelMatches::default();
                let mut first_pyramid = SiftPyramid::default();
                first_pyramid.build(&first, &config.sift_flow).expect("pyramid");
                let (api_cpu, (api_wall, ())) = cpu_time(|| {
                    time(|| {
                        match_sift_images(&first, &first_pyramid, &second, None, &config, &mut pair_workspace, &mut out)
                            .expect("pair")
                    })
                });
                println!(
                    "{} pair both ways, {threads} thread(s): separate flows {:.0} ms wall / {:.0} ms CPU; pair API {:.0} ms wall / {:.0} ms CPU",
                    pair.name,
                    separate_wall.as_secs_f64() * 1000.0,
                    separate_cpu.as_secs_f64() * 1000.0,
                    api_wall.as_secs_f64() * 1000.0,
                    api_cpu.as_secs_f64() * 1000.0
                );
            });
        }
        let descriptors = first.descriptors.len() / 128;
        for kernel in [L1Kernel::Portable, L1Kernel::Sse2, L1Kernel::Avx2] {
            let (elapsed, total) = time(|| {
                let mut total = 0u64;
                for pixel in 0..descriptors - 1 {
                    total += descriptor_l1_distance(
                        first.descriptor(pixel),
                        second.descriptor(pixel + 1),
                        kernel,
                    ) as u64;
                }
                total
            });
            black_box(total);
            println!(
                "{} L1 distance {kernel:?}: {:.2} ns per descriptor pair (with per-call dispatch)",
                pair.name,
                elapsed.as_secs_f64() * 1e9 / descriptors as f64
            );
        }
    }
    if let Some(pair) = pairs.first() {
        let renderings: Vec<(ImageView<f32>, Option<ImageView<bool>>)> =
            (0..30).map(|_| (pair.second.view(), None)).collect();
        for (preset, sift_flow) in presets
            .iter()
            .filter(|(preset, _)| preset.starts_with("fast"))
        {
            let config = MatchConfig {
                sift_flow: sift_flow.clone(),
                ..Default::default()
            };
            let first = sift(pair.first.view());
            let second = sift(pair.second.view());
            let mut first_pyramid = SiftPyramid::default();
            let mut second_pyramid = SiftPyramid::default();
            first_pyramid.build(&first, sift_flow).expect("pyramid");
            second_pyramid.build(&second, sift_flow).expect("pyramid");
            for threads in [1, 2] {
                let (cpu, (wall, count)) = cpu_time(|| {
                    time(|| {
                        pool(threads).install(|| {
                            (0..30)
                                .into_par_iter()
                                .map_init(SiftFlowWorkspace::default, |workspace, _| {
                                    let mut field = FlowField::default();
                                    let mut cost = Image::default();
                                    compute_sift_flow_on_pyramids(
                                        (&first, &first_pyramid, None),
                                        (&second, &second_pyramid, None),
                                        sift_flow,
                                        workspace,
                                        &mut field,
                                        &mut cost,
                                    )
                                    .expect("SIFT flow")
                                })
                                .count()
                        })
                    })
                });
                println!(
                    "{} frame, {preset}: {count} SIFT flows (pyramids given), {threads} thread(s): {:.0} ms wall, {:.0} ms CPU",
                    pair.name,
                    wall.as_secs_f64() * 1000.0,
                    cpu.as_secs_f64() * 1000.0
                );
            }
            let (cpu, (wall, results)) = cpu_time(|| {
                time(|| {
                    pool(2).install(|| {
                        match_query_to_renderings(pair.first.view(), &renderings, &config)
                            .expect("frame")
                    })
                })
            });
            println!(
                "{} frame, {preset}: 30 pairs both ways + dense SIFT + consistency, 2 threads: {:.0} ms wall, {:.0} ms CPU, {} matches per pair",
                pair.name,
                wall.as_secs_f64() * 1000.0,
                cpu.as_secs_f64() * 1000.0,
                results.first().map_or(0, |result| result.matches.len())
            );
        }
    }
}

fn criterion_benches(criterion: &mut Criterion, pairs: &[Pair]) {
    let mut group = criterion.benchmark_group("dense_sift");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(5));
    for pair in pairs {
        for threads in [1, 2] {
            let thread_pool = pool(threads);
            let mut workspace = DenseSiftWorkspace::default();
            let mut out = DenseSiftImage::default();
            group.bench_function(
                BenchmarkId::new(pair.name, format!("{threads}t")),
                |bench| {
                    bench.iter(|| {
                        thread_pool.install(|| {
                            compute_dense_sift(
                                pair.first.view(),
                                &DenseSiftConfig::default(),
                                &mut workspace,
                                &mut out,
                            )
                        })
                    })
                },
            );
        }
    }
    group.finish();

    let mut group = criterion.benchmark_group("sift_flow");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(10));
    for pair in pairs {
        let first = sift(pair.first.view());
        let second = sift(pair.second.view());
        let variants = [
            ("default", SiftFlowConfig::default()),
            ("fast", SiftFlowConfig::fast()),
        ];
        for (variant, config) in &variants {
            for threads in [1, 2] {
                let thread_pool = pool(threads);
                let mut workspace = SiftFlowWorkspace::default();
                group.bench_function(
                    BenchmarkId::new(pair.name, format!("{variant}/{threads}t")),
                    |bench| {
                        bench.iter(|| {
                            thread_pool.install(|| flow(&first, &second, config, &mut workspace))
                        })
                    },
                );
            }
        }
    }
    group.finish();

    if let Some(pair) = pairs.first() {
        let first = sift(pair.first.view());
        let second = sift(pair.second.view());
        let mut group = criterion.benchmark_group("frame");
        group
            .sample_size(10)
            .measurement_time(Duration::from_secs(30));
        let thread_pool = pool(2);
        group.bench_function(
            BenchmarkId::new("30_pairs_fast_preset", pair.name),
            |bench| {
                bench.iter(|| {
                    thread_pool.install(|| {
                        (0..30)
                            .into_par_iter()
                            .map_init(SiftFlowWorkspace::default, |workspace, _| {
                                flow(&first, &second, &SiftFlowConfig::fast(), workspace)
                            })
                            .count()
                    })
                })
            },
        );
        group.finish();
    }
}

fn main() {
    let pairs: Vec<Pair> = [
        ("dji0024_505x275", "tests/data/flow-pairs"),
        ("dji0024_1010x550", "../shared/data/flow-pairs"),
    ]
    .into_iter()
    .filter_map(load_pair)
    .collect();
    assert!(
        !pairs.is_empty(),
        "tests/data/flow-pairs is part of the repository: the 505×275 pair must be there"
    );
    if std::env::var_os("FLOW_BENCH_ITERATIONS").is_some() {
        for pair in &pairs {
            let first = sift(pair.first.view());
            let second = sift(pair.second.view());
            let mut workspace = SiftFlowWorkspace::default();
            pool(1).install(|| {
                for (iterations, top_iterations, max_multigrid_depth, multigrid_iterations) in [(4, 20, 8, 4), (4, 10, 8, 4), (4, 20, 2, 4), (4, 20, 1, 4), (4, 12, 2, 4), (8, 20, 1, 4), (8, 12, 0, 4)] {
                    let config = SiftFlowConfig { iterations, top_iterations, max_multigrid_depth, multigrid_iterations, ..Default::default() };
                    let (cpu, field) = cpu_time(|| flow(&first, &second, &config, &mut workspace));
                    let (epe, under_one) = score(&field, &pair.truth);
                    println!("{} iterations {iterations}/{top_iterations} depth {max_multigrid_depth} multigrid iterations {multigrid_iterations}: CPU {:.0} ms, EPE {epe:.3}, < 1 px {under_one:.3}", pair.name, cpu.as_secs_f64() * 1000.0);
                }
            });
        }
        return;
    }
    if std::env::var_os("FLOW_BENCH_PROFILE").is_some() {
        // One pair, three flows on one thread: a target for `perf record`.
        if let Some(pair) = pairs.first() {
            let first = sift(pair.first.view());
            let second = sift(pair.second.view());
            let mut workspace = SiftFlowWorkspace::default();
            pool(1).install(|| {
                for _ in 0..3 {
                    let mut field = FlowField::default();
                    let mut cost = Image::default();
                    let timings = compute_sift_flow(
                        &first,
                        None,
                        &second,
                        None,
                        &SiftFlowConfig::default(),
                        &mut workspace,
                        &mut field,
                        &mut cost,
                    )
                    .expect("SIFT flow");
                    println!("{timings:?}");
                }
            });
        }
        return;
    }
    if std::env::var_os("FLOW_BENCH_STAGES").is_some() {
        stages_report(&pairs);
        return;
    }
    if std::env::var_os("FLOW_BENCH_QUICK").is_some() {
        quick_report(&pairs);
        return;
    }
    let mut criterion = Criterion::default().configure_from_args();
    criterion_benches(&mut criterion, &pairs);
    criterion.final_summary();
}
