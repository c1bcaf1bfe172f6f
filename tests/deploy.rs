//! deploy/ checked without a container engine (issue 11, point 5): every YAML file parses;
//! every `lightmapd` command line in the compose file, the Kubernetes manifests, the
//! systemd unit and the Dockerfile names a real subcommand and real flags, and is accepted
//! by the real binary's parser (run with `--help` appended after its variables are
//! resolved, so a bad value such as a malformed `--store` fails too); every variable those
//! command lines use is defined where it is expanded (compose defaults, the pod's env,
//! ConfigMap and Secret keys, the unit's `Environment=`); compose images are pinned or
//! built from a Dockerfile that exists; the Kubernetes worker requests `nvidia.com/gpu`;
//! the queue query of the scaling example names a real table, column and states; and
//! docs/deploy.md's configuration reference lists every flag of `serve` and `worker`.
//!
//! What this cannot check: that an image tag exists on its registry (no registry is
//! reachable from CI), and anything that needs Docker or a cluster to run.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Command;

use serde_norway::Value;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Every document of a YAML file, with `<<` merge keys applied.
fn documents(path: &Path) -> Vec<Value> {
    let text = read(path);
    serde_norway::Deserializer::from_str(&text)
        .map(|d| {
            let mut v: Value = serde::Deserialize::deserialize(d).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            v.apply_merge().unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            v
        })
        .filter(|v| !v.is_null())
        .collect()
}

fn yaml_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            yaml_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "yaml" || x == "yml") {
            out.push(p);
        }
    }
    out.sort();
}

fn s(v: &Value) -> &str {
    v.as_str().unwrap_or_else(|| panic!("expected a string, got {v:?}"))
}

fn strings(v: &Value) -> Vec<String> {
    v.as_sequence()
        .map(|seq| {
            seq.iter()
                .map(|x| match x {
                    Value::String(t) => t.clone(),
                    Value::Number(n) => n.to_string(),
                    Value::Bool(b) => b.to_string(),
                    other => panic!("not a scalar: {other:?}"),
                })
                .collect()
        })
        .unwrap_or_default()
}

/// The subcommands and, per subcommand, the long flags of the real binary, read from its
/// `--help`.
struct Cli {
    flags: BTreeMap<String, BTreeSet<String>>,
}

impl Cli {
    fn load() -> Cli {
        let help = |args: &[&str]| {
            let out = Command::new(env!("CARGO_BIN_EXE_lightmapd"))
                .args(args)
                .output()
                .unwrap();
            assert!(out.status.success(), "lightmapd {args:?} failed");
            String::from_utf8(out.stdout).unwrap()
        };
        let top = help(&["--help"]);
        let subcommands: Vec<String> = top
            .lines()
            .skip_while(|l| !l.starts_with("Commands:"))
            .skip(1)
            .take_while(|l| l.starts_with(' '))
            .filter_map(|l| l.split_whitespace().next().map(str::to_string))
            .filter(|c| c != "help")
            .collect();
        assert!(subcommands.iter().any(|c| c == "serve"), "{top}");
        let flags = subcommands
            .iter()
            .map(|c| {
                let text = help(&[c, "--help"]);
                (c.clone(), long_flags(&text))
            })
            .collect();
        Cli { flags }
    }

    /// Checks one command line (without the program name) and runs the real parser on it.
    fn check(&self, args: &[String], origin: &str) {
        let sub = args.first().unwrap_or_else(|| panic!("{origin}: no subcommand"));
        let known = self
            .flags
            .get(sub)
            .unwrap_or_else(|| panic!("{origin}: `lightmapd {sub}` is not a subcommand"));
        for a in args.iter().filter(|a| a.starts_with("--")) {
            let name = a.split('=').next().unwrap();
            assert!(
                known.contains(name),
                "{origin}: `lightmapd {sub}` has no flag {name} (it has {known:?})"
            );
        }
        assert!(
            !args.iter().any(|a| a.contains('$')),
            "{origin}: unresolved variable in {args:?}"
        );
        let out = Command::new(env!("CARGO_BIN_EXE_lightmapd"))
            .args(args)
            .arg("--help")
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{origin}: lightmapd {args:?} is refused: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
}

fn long_flags(help: &str) -> BTreeSet<String> {
    help.lines()
        .map(str::trim_start)
        .filter(|l| l.starts_with("--") || l.starts_with('-') && l.get(2..4) == Some(", "))
        .filter_map(|l| {
            l.split([' ', ',', '='])
                .find(|w| w.starts_with("--"))
                .map(str::to_string)
        })
        .collect()
}

/// Replaces `${NAME}`, `${NAME:-default}` and `${NAME-default}` (compose, systemd) or
/// `$(NAME)` (Kubernetes) through `lookup`; a variable it cannot resolve is a failure.
fn expand(text: &str, k8s: bool, lookup: &dyn Fn(&str, Option<&str>) -> Option<String>, origin: &str) -> String {
    let mut out = String::new();
    let mut rest = text;
    let (open, close) = if k8s { ("$(", ')') } else { ("${", '}') };
    while let Some(i) = rest.find(open) {
        out.push_str(&rest[..i]);
        // Nested defaults (`${A:-${B}}`) are not used in deploy/; the first `}` closes.
        let body_end = rest[i..]
            .find(close)
            .unwrap_or_else(|| panic!("{origin}: unclosed {open} in {text:?}"));
        let body = &rest[i + 2..i + body_end];
        let (name, default) = match body.split_once(":-").or_else(|| body.split_once('-')) {
            Some((n, d)) if !k8s => (n, Some(d)),
            _ => (body, None),
        };
        let value = lookup(name, default).unwrap_or_else(|| panic!("{origin}: variable {name} is not defined"));
        out.push_str(&value);
        rest = &rest[i + body_end + 1..];
    }
    out.push_str(rest);
    out
}

fn deploy() -> PathBuf {
    root().join("deploy")
}

#[test]
fn every_yaml_file_parses() {
    let mut files = Vec::new();
    yaml_files(&deploy(), &mut files);
    assert!(files.len() >= 8, "deploy/ has only {files:?}");
    for f in &files {
        let docs = documents(f);
        assert!(!docs.is_empty(), "{} is empty", f.display());
        for d in &docs {
            assert!(d.is_mapping(), "{}: a document is not a mapping", f.display());
        }
    }
}

#[test]
fn compose_services_and_command_lines_are_real() {
    let cli = Cli::load();
    let path = deploy().join("compose.yaml");
    let text = read(&path);
    // Compose variables: every `${VAR}` has a default, so the file works with no .env.
    // `$$` is compose's escape for a literal `$` (used inside containers' own shells).
    let unescaped = text.replace("$$", "");
    let compose_lookup = |name: &str, default: Option<&str>| {
        assert!(!name.is_empty());
        default.map(str::to_string)
    };
    let _ = expand(&unescaped, false, &compose_lookup, "compose.yaml");

    let doc = documents(&path).remove(0);
    let services = doc["services"].as_mapping().expect("compose.yaml has services");
    let names: BTreeSet<String> = services.keys().map(|k| s(k).to_string()).collect();
    let (mut apis, mut workers) = (0, 0);
    for (name, svc) in services {
        let name = s(name);
        let origin = format!("compose.yaml: service {name}");
        // An image comes from a build whose Dockerfile exists, or is pinned to a tag.
        if let Some(build) = svc.get("build") {
            let context = deploy().join(s(&build["context"]));
            let dockerfile = context.join(build.get("dockerfile").map_or("Dockerfile", s));
            assert!(
                dockerfile.is_file(),
                "{origin}: {} does not exist",
                dockerfile.display()
            );
        } else {
            let image = s(&svc["image"]);
            let tag = image.rsplit_once(':').map(|(_, t)| t).unwrap_or("");
            assert!(
                !tag.is_empty() && tag != "latest" && !tag.contains('/'),
                "{origin}: image {image} is not pinned to a tag"
            );
        }
        for (dep, cond) in svc.get("depends_on").and_then(Value::as_mapping).into_iter().flatten() {
            let dep = s(dep);
            assert!(names.contains(dep), "{origin}: depends on unknown service {dep}");
            let cond = s(&cond["condition"]);
            if cond == "service_healthy" {
                assert!(
                    services[dep].get("healthcheck").is_some(),
                    "{origin}: waits for {dep} to be healthy, which has no healthcheck"
                );
            }
        }
        let args = strings(&svc["command"]);
        let is_lightmapd = svc.get("build").is_some();
        if !is_lightmapd {
            continue;
        }
        let args: Vec<String> = args
            .iter()
            .map(|a| expand(a, false, &compose_lookup, &origin))
            .collect();
        cli.check(&args, &origin);
        let env = svc["environment"]
            .as_mapping()
            .expect("lightmapd services have an environment");
        let env_value = |k: &str| env.get(k).map(|v| expand(s(v), false, &compose_lookup, &origin));
        // The S3 endpoint and the database host are services of this file.
        let endpoint = env_value("AWS_ENDPOINT_URL").unwrap_or_else(|| panic!("{origin}: no AWS_ENDPOINT_URL"));
        let host = endpoint.trim_start_matches("http://").split([':', '/']).next().unwrap();
        assert!(names.contains(host), "{origin}: S3 endpoint {endpoint} is no service");
        for key in ["AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_REGION"] {
            assert!(env_value(key).is_some(), "{origin}: {key} is not set");
        }
        assert_eq!(
            env_value("AWS_ALLOW_HTTP").as_deref(),
            Some("true"),
            "{origin}: http endpoint"
        );
        // The database URL holds a password: from the environment, never in argv.
        assert!(
            !args.iter().any(|a| a == "--database-url"),
            "{origin}: --database-url in argv shows the password in the process list"
        );
        let db = env_value("LIGHTMAPD_DATABASE_URL").unwrap_or_else(|| panic!("{origin}: no LIGHTMAPD_DATABASE_URL"));
        let db = &db;
        let db_host = db
            .split('@')
            .nth(1)
            .and_then(|h| h.split([':', '/']).next())
            .unwrap_or("");
        assert!(
            names.contains(db_host),
            "{origin}: database host {db_host} is no service"
        );
        let store = args.iter().position(|a| a == "--store").map(|i| &args[i + 1]);
        assert!(
            store.is_some_and(|s| s.starts_with("s3://")),
            "{origin}: no s3:// store"
        );
        match args[0].as_str() {
            "serve" => {
                let w = args.iter().position(|a| a == "--workers").map(|i| args[i + 1].as_str());
                assert_eq!(w, Some("0"), "{origin}: the API runs no bakes");
                assert!(svc.get("healthcheck").is_some(), "{origin}: no healthcheck");
                // Tokens required, from a compose secret that the file defines.
                assert!(args.iter().any(|a| a == "--auth"), "{origin}: no --auth");
                let tokens = env_value("LIGHTMAPD_TOKENS_FILE").unwrap_or_else(|| panic!("{origin}: no tokens file"));
                let secret = tokens.strip_prefix("/run/secrets/").expect("a compose secret");
                assert!(
                    strings(&svc["secrets"]).contains(&secret.to_string()),
                    "{origin}: secret {secret} not mounted"
                );
                assert!(
                    doc["secrets"][secret]["file"].as_str().is_some(),
                    "{origin}: secret {secret} undefined"
                );
                apis += 1;
            }
            "worker" => {
                workers += svc["deploy"]["replicas"].as_u64().unwrap_or(1);
                assert!(
                    args.iter().any(|a| a == "--database-timeout-s"),
                    "{origin}: a worker without its database must exit for `restart` to help"
                );
            }
            other => panic!("{origin}: unexpected subcommand {other}"),
        }
    }
    assert_eq!((apis, workers), (1, 2), "one API and two workers");
    for needed in ["postgres", "minio", "create-bucket"] {
        assert!(names.contains(needed), "compose.yaml has no {needed}");
    }

    // The GPU overlay only adds to services of the base file.
    let gpu = documents(&deploy().join("compose.gpu.yaml")).remove(0);
    for (name, svc) in gpu["services"].as_mapping().unwrap() {
        assert!(names.contains(s(name)), "compose.gpu.yaml: unknown service {name:?}");
        let devices = &svc["deploy"]["resources"]["reservations"]["devices"][0];
        assert_eq!(s(&devices["driver"]), "nvidia");
        assert!(strings(&devices["capabilities"]).contains(&"graphics".to_string()));
    }
}

/// All Kubernetes objects of deploy/k8s, by kind and name.
fn k8s_objects() -> Vec<(PathBuf, Value)> {
    let mut files = Vec::new();
    yaml_files(&deploy().join("k8s"), &mut files);
    files
        .into_iter()
        .filter(|f| f.file_name().unwrap() != "kustomization.yaml")
        .flat_map(|f| documents(&f).into_iter().map(move |d| (f.clone(), d)))
        .collect()
}

fn find<'a>(objects: &'a [(PathBuf, Value)], kind: &str, name: &str) -> Option<&'a Value> {
    objects
        .iter()
        .map(|(_, o)| o)
        .find(|o| o["kind"].as_str() == Some(kind) && o["metadata"]["name"].as_str() == Some(name))
}

#[test]
fn kubernetes_manifests_are_consistent() {
    let cli = Cli::load();
    let objects = k8s_objects();
    for (f, o) in &objects {
        for key in ["apiVersion", "kind"] {
            assert!(o.get(key).is_some(), "{}: an object has no {key}", f.display());
        }
        assert!(
            o["metadata"]["name"].as_str().is_some(),
            "{}: unnamed object",
            f.display()
        );
    }
    // kustomization.yaml lists every manifest, and only existing ones.
    let kust = documents(&deploy().join("k8s/kustomization.yaml")).remove(0);
    let listed: BTreeSet<String> = strings(&kust["resources"]).into_iter().collect();
    let on_disk: BTreeSet<String> = objects
        .iter()
        .map(|(f, _)| f.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    assert_eq!(listed, on_disk, "kustomization.yaml resources vs files in deploy/k8s");

    let (mut api, mut worker) = (false, false);
    for (f, o) in objects.iter().filter(|(_, o)| o["kind"] == "Deployment") {
        let name = s(&o["metadata"]["name"]);
        let spec = &o["spec"]["template"]["spec"];
        for c in spec["containers"].as_sequence().unwrap() {
            let origin = format!("{}: {name}/{}", f.display(), s(&c["name"]));
            if s(&c["image"]).split(':').next() != Some("lightmapd") {
                continue;
            }
            // `$(VAR)` in args: the container's env, or a key of an envFrom ConfigMap/Secret.
            let lookup = |var: &str, _: Option<&str>| -> Option<String> {
                for e in c["env"].as_sequence().into_iter().flatten() {
                    if e["name"].as_str() == Some(var) {
                        return e["value"].as_str().map(str::to_string);
                    }
                }
                for from in c["envFrom"].as_sequence().into_iter().flatten() {
                    let (kind, r) = if let Some(r) = from.get("configMapRef") {
                        ("ConfigMap", r)
                    } else {
                        ("Secret", &from["secretRef"])
                    };
                    let obj = find(&objects, kind, s(&r["name"]))
                        .unwrap_or_else(|| panic!("{origin}: no {kind} {:?}", r["name"]));
                    for section in ["data", "stringData"] {
                        if let Some(v) = obj[section].get(var) {
                            return Some(s(v).to_string());
                        }
                    }
                }
                None
            };
            let args: Vec<String> = strings(&c["args"])
                .iter()
                .map(|a| expand(a, true, &lookup, &origin))
                .collect();
            cli.check(&args, &origin);
            assert!(
                !args.iter().any(|a| a == "--database-url"),
                "{origin}: --database-url in argv shows the password in the pod spec"
            );
            assert!(
                lookup("LIGHTMAPD_DATABASE_URL", None).is_some(),
                "{origin}: no LIGHTMAPD_DATABASE_URL"
            );
            let gpus = c["resources"]["limits"]["nvidia.com/gpu"].as_u64();
            match args[0].as_str() {
                "serve" => {
                    api = true;
                    assert_eq!(gpus, None, "{origin}: the API needs no GPU");
                    let w = args.iter().position(|a| a == "--workers").map(|i| args[i + 1].as_str());
                    assert_eq!(w, Some("0"), "{origin}: the API runs no bakes");
                    let port = c["ports"][0]["containerPort"].as_u64().unwrap();
                    let listen = args.iter().position(|a| a == "--listen").map(|i| args[i + 1].as_str());
                    assert_eq!(listen, Some(format!("0.0.0.0:{port}").as_str()), "{origin}");
                    assert_eq!(s(&c["readinessProbe"]["httpGet"]["path"]), "/healthz", "{origin}");
                    assert!(args.iter().any(|a| a == "--auth"), "{origin}: no --auth");
                    // The tokens file is a mounted Secret.
                    let file =
                        lookup("LIGHTMAPD_TOKENS_FILE", None).unwrap_or_else(|| panic!("{origin}: no tokens file"));
                    let mount = c["volumeMounts"]
                        .as_sequence()
                        .unwrap()
                        .iter()
                        .find(|m| file.starts_with(s(&m["mountPath"])))
                        .unwrap_or_else(|| panic!("{origin}: {file} is on no volume"));
                    let volume = spec["volumes"]
                        .as_sequence()
                        .unwrap()
                        .iter()
                        .find(|v| v["name"] == mount["name"])
                        .unwrap();
                    let secret =
                        find(&objects, "Secret", s(&volume["secret"]["secretName"])).expect("the tokens Secret");
                    let key = file.rsplit('/').next().unwrap();
                    assert!(
                        secret["stringData"].get(key).is_some(),
                        "{origin}: the Secret has no key {key}"
                    );
                }
                "worker" => {
                    worker = true;
                    assert!(
                        args.iter().any(|a| a == "--database-timeout-s"),
                        "{origin}: no --database-timeout-s"
                    );
                    assert_eq!(gpus, Some(1), "{origin}: a worker requests one nvidia.com/gpu");
                    let caps = lookup("NVIDIA_DRIVER_CAPABILITIES", None).unwrap_or_default();
                    assert!(
                        caps.contains("graphics"),
                        "{origin}: Vulkan needs the graphics capability"
                    );
                }
                other => panic!("{origin}: unexpected subcommand {other}"),
            }
        }
    }
    assert!(api && worker, "an API and a worker Deployment");

    // The Service selects the API pods and targets a port they have.
    let svc = find(&objects, "Service", "lightmapd-api").expect("Service lightmapd-api");
    let api_dep = find(&objects, "Deployment", "lightmapd-api").unwrap();
    let labels = api_dep["spec"]["template"]["metadata"]["labels"].as_mapping().unwrap();
    for (k, v) in svc["spec"]["selector"].as_mapping().unwrap() {
        assert_eq!(labels.get(k), Some(v), "Service selector {k:?}");
    }
    let target = s(&svc["spec"]["ports"][0]["targetPort"]);
    let ports = &api_dep["spec"]["template"]["spec"]["containers"][0]["ports"];
    assert!(ports.as_sequence().unwrap().iter().any(|p| p["name"] == target));

    // The scaling example: its target, its secret, and a query on the real schema.
    let so = objects
        .iter()
        .map(|(_, o)| o)
        .find(|o| o["kind"] == "ScaledObject")
        .expect("a ScaledObject");
    let target = s(&so["spec"]["scaleTargetRef"]["name"]);
    let dep = find(&objects, "Deployment", target).expect("the ScaledObject scales a Deployment");
    assert!(
        strings(&dep["spec"]["template"]["spec"]["containers"][0]["args"])
            .first()
            .map(String::as_str)
            == Some("worker")
    );
    let trigger = &so["spec"]["triggers"][0];
    let auth = find(
        &objects,
        "TriggerAuthentication",
        s(&trigger["authenticationRef"]["name"]),
    )
    .expect("its auth");
    for r in auth["spec"]["secretTargetRef"].as_sequence().unwrap() {
        let secret = find(&objects, "Secret", s(&r["name"])).expect("the auth's Secret");
        assert!(
            secret["stringData"].get(s(&r["key"])).is_some(),
            "Secret key {:?}",
            r["key"]
        );
    }
    check_queue_query(s(&trigger["metadata"]["query"]));
}

/// The table, column and states the query names exist in the migrations.
fn check_queue_query(query: &str) {
    let mut schema = String::new();
    for dir in std::fs::read_dir(root().join("migrations")).unwrap() {
        for f in std::fs::read_dir(dir.unwrap().path()).unwrap() {
            schema.push_str(&read(&f.unwrap().path()));
        }
    }
    let jobs = schema.find("CREATE TABLE jobs").expect("a jobs table");
    let table = &schema[jobs..jobs + schema[jobs..].find(");").unwrap()];
    assert!(query.contains("FROM jobs WHERE status"), "{query}");
    assert!(table.contains("status "), "jobs has no status column");
    let states: Vec<&str> = query.split('\'').skip(1).step_by(2).collect();
    assert!(!states.is_empty(), "{query}");
    for st in states {
        assert!(
            table.contains(&format!("'{st}'")),
            "state {st:?} is not one of the jobs table's"
        );
    }
}

#[test]
fn systemd_unit_and_dockerfile_command_lines_are_real() {
    let cli = Cli::load();
    // systemd: Environment= defines what ExecStart's ${VAR} expand to.
    let unit = read(&deploy().join("systemd/lightmapd.service"));
    let mut env = BTreeMap::new();
    let mut exec = None;
    for line in unit.lines().map(str::trim) {
        if let Some(kv) = line.strip_prefix("Environment=") {
            let (k, v) = kv.split_once('=').expect("Environment=K=V");
            env.insert(k.to_string(), v.to_string());
        } else if let Some(cmd) = line.strip_prefix("ExecStart=") {
            exec = Some(cmd.to_string());
        }
    }
    for needed in [
        "NoNewPrivileges=yes",
        "ProtectSystem=strict",
        "DynamicUser=yes",
        "StateDirectory=lightmapd",
    ] {
        assert!(unit.lines().any(|l| l.trim() == needed), "the unit lacks {needed}");
    }
    // lavapipe and GPU drivers JIT-compile shaders: W^X would break every GPU bake.
    assert!(!unit.contains("\nMemoryDenyWriteExecute=yes"));
    let exec = exec.expect("ExecStart=");
    let lookup = |k: &str, _: Option<&str>| env.get(k).cloned();
    let words: Vec<String> = exec
        .split_whitespace()
        .map(|w| expand(w, false, &lookup, "lightmapd.service"))
        .collect();
    assert!(words[0].ends_with("/lightmapd"), "{exec}");
    cli.check(&words[1..], "lightmapd.service ExecStart");
    assert!(words.iter().any(|w| w == "--auth"), "the unit serves without --auth");
    assert_eq!(env.get("LIGHTMAPD_TOKENS_FILE").map(String::as_str), Some("%d/tokens"));
    assert!(
        unit.lines()
            .any(|l| l.trim() == "LoadCredential=tokens:/etc/lightmapd/tokens")
    );

    // The Dockerfile: its default command, what it copies, what it installs.
    let docker = read(&deploy().join("Dockerfile"));
    let json_array = |instr: &str| -> Vec<String> {
        let line = docker
            .lines()
            .find(|l| l.starts_with(instr))
            .unwrap_or_else(|| panic!("no {instr}"));
        serde_json::from_str(line[instr.len()..].trim()).unwrap()
    };
    assert_eq!(json_array("ENTRYPOINT"), vec!["lightmapd".to_string()]);
    cli.check(&json_array("CMD"), "Dockerfile CMD");
    assert!(
        json_array("CMD").contains(&"--auth".to_string()),
        "the image serves without --auth"
    );
    for line in docker
        .lines()
        .filter(|l| l.starts_with("COPY ") && !l.contains("--from"))
    {
        let parts: Vec<&str> = line.split_whitespace().collect();
        for src in &parts[1..parts.len() - 1] {
            assert!(
                root().join(src).exists(),
                "Dockerfile copies {src}, which does not exist"
            );
        }
    }
    assert!(docker.contains("cargo build --release --locked"));
    for pkg in ["libvulkan1", "mesa-vulkan-drivers"] {
        assert!(docker.contains(pkg), "the runtime image lacks {pkg}");
    }
    let user = docker.lines().rfind(|l| l.starts_with("USER ")).expect("USER");
    assert!(!user.contains("root") && !user.contains(" 0"), "{user}");
    assert!(docker.contains("NVIDIA_DRIVER_CAPABILITIES=compute,graphics,utility"));
    let icd: serde_json::Value = serde_json::from_str(&read(&deploy().join("nvidia_icd.json"))).unwrap();
    assert!(icd["ICD"]["library_path"].as_str().is_some());
}

#[test]
fn the_configuration_reference_lists_every_flag() {
    let cli = Cli::load();
    let doc = read(&root().join("docs/deploy.md"));
    for sub in ["serve", "worker"] {
        for flag in &cli.flags[sub] {
            if flag == "--help" {
                continue;
            }
            assert!(
                doc.contains(&format!("`{flag}")),
                "docs/deploy.md does not describe `lightmapd {sub} {flag}`"
            );
        }
    }
}
