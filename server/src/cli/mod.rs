//! The binary's commands, one module per concern (data sets, tessellation, simulation,
//! serving), the terminal progress bar they share, and the data set opened for serving
//! that `serve`, `world`, `edge`, `bus-load` and `color-bench` share (`served`).

pub mod bus_load;
pub mod cluster;
pub mod color_bench;
pub mod data;
pub mod identity;
pub mod import;
pub mod net;
pub mod progress;
pub mod served;
pub mod sim;
pub mod tess;
pub mod token;
