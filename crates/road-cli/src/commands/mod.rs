pub mod data;
pub mod gpu;
pub mod sched;
pub mod train;
