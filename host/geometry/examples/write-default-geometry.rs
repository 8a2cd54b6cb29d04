//! Regenerates the shipped default geometry file from
//! `ScannerGeometry::generate_default` (after changing the default layout):
//! `cargo run -p scanner-geometry --example write-default-geometry`.

fn main() -> std::io::Result<()> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/config/default-geometry.toml");
    std::fs::write(path, scanner_geometry::ScannerGeometry::generate_default().to_toml())?;
    println!("wrote {path}");
    Ok(())
}
