//! The shipped presets: `presets/` holds what `procl config` resolves for every preset,
//! environment and method, and each file trains as the preset itself does.

use std::path::Path;

use procl::envs::EnvKind;
use procl::train::{Method, config_from_table, config_from_toml};

#[test]
fn presets_are_the_shipped_configurations() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("presets");
    for preset in ["procl", "paper"] {
        for env in [EnvKind::PointMass, EnvKind::Reacher, EnvKind::Fetch] {
            for method in [Method::Procl, Method::Pc3, Method::Nvae] {
                let mut table = toml::Table::new();
                table.insert("preset".into(), toml::Value::String(preset.into()));
                let resolved = config_from_table(table, env, Some(method)).unwrap();
                let name = format!("{preset}/{env}-{}.toml", method.dir_name());
                let path = root.join(&name);
                let shipped = std::fs::read_to_string(&path).unwrap();
                assert_eq!(
                    toml::to_string(&resolved).unwrap(),
                    shipped,
                    "presets/{name} differs from the code's preset; if the change is meant, \
                     rewrite it with `procl config --env {env} --method {} --preset {preset}`",
                    method.dir_name()
                );
                // The file read back as a config gives the preset itself.
                assert_eq!(
                    config_from_toml(&path, env, None).unwrap(),
                    resolved,
                    "{name}"
                );
            }
        }
    }
}

#[test]
fn a_config_for_another_environment_is_refused() {
    let table: toml::Table = "env = \"fetch\"".parse().unwrap();
    let err = config_from_table(table, EnvKind::Reacher, None)
        .unwrap_err()
        .to_string();
    assert!(err.contains("env") && err.contains("fetch"), "{err}");
}
