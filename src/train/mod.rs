pub mod cameras;
pub mod config;
pub mod deformed;
