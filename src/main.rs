//! The `asgreg` command line: parses arguments and wires them to the library.

fn main() -> anyhow::Result<()> {
    Ok(())
}
