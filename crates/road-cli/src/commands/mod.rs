pub mod bench;
pub mod data;
pub mod eval;
pub mod gpu;
pub mod sample;
pub mod sched;
pub mod train;
