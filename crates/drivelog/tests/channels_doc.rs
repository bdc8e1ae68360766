//! The README's "Logs" table is where the channels are written down: it names every channel
//! the logs have, with its message type, and no other.

use drivelog::Channel;

#[test]
fn the_readmes_table_names_every_channel_with_its_type() {
    let readme = include_str!("../../../README.md");
    let logs = readme
        .split("\n## ")
        .find(|section| section.starts_with("Logs\n"))
        .expect("README.md has a Logs section");
    let rows: Vec<(&str, &str)> = logs
        .lines()
        .filter_map(|l| {
            let mut cells = l.split('|').map(str::trim).skip(1);
            let topic = cells.next()?.strip_prefix("`/")?.strip_suffix('`')?;
            let kind = cells.next()?.strip_prefix('`')?.strip_suffix('`')?;
            Some((topic, kind))
        })
        .collect();
    let code: Vec<(&str, &str)> = Channel::ALL
        .iter()
        .map(|c| (&c.topic()[1..], c.def().name))
        .collect();
    assert_eq!(
        rows, code,
        "README.md's Logs table against drivelog::Channel::ALL"
    );
}
