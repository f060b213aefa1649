pub mod bench;
pub mod compare;
pub mod data;
pub mod demo;
pub mod demo_zenoh;
pub mod ego;
pub mod engine;
pub mod eval;
pub mod flood;
pub mod fuzz;
pub mod gpu;
pub mod gpu_options;
pub mod recover;
pub mod render;
pub mod replay;
pub mod router;
pub mod sample;
pub mod sched;
pub mod serve;
pub mod soak;
pub mod train;
pub mod zenoh_bench;

/// Loads a split's cache from `cache_dir`, checked against the default window settings.
pub(crate) fn load_cache(
    cache_dir: &std::path::Path,
    split: road_data::Split,
) -> anyhow::Result<road_data::Dataset> {
    use anyhow::Context;
    road_data::cache::load_checked(
        &road_data::cache::cache_path(cache_dir, split),
        split,
        Some(&road_data::WindowConfig::default()),
        None,
    )
    .with_context(|| format!("the {split} cache is needed: run `road data build`"))
}
