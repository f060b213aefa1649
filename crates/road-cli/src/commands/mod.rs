pub mod bench;
pub mod data;
pub mod gpu;
pub mod sample;
pub mod sched;
pub mod train;
