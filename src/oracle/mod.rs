pub mod loss;
pub mod rasterize;
