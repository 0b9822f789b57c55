"""Server settings given to the measuring scripts (`profile`, `live`) as `--set SECTION.KEY=VALUE`
(values are TOML, e.g. `markers.threshold_windows="one"`), over each script's own defaults,
written as the TOML file the server's `--config` reads."""
import re
import sys


def with_sets(defaults, items, script):
    """`defaults` ({section: {key: TOML value}}) with every `--set` item applied over them."""
    settings = {section: dict(values) for section, values in defaults.items()}
    for item in items:
        m = re.fullmatch(r"([a-z_]+)\.([a-z_]+)=(.+)", item)
        if not m:
            sys.exit(f"{script}: --set wants SECTION.KEY=VALUE, got {item!r}")
        settings.setdefault(m.group(1), {})[m.group(2)] = m.group(3)
    return settings


def write_toml(path, settings):
    with open(path, "w") as f:
        for section, values in settings.items():
            f.write(f"[{section}]\n" + "".join(f"{k} = {v}\n" for k, v in values.items()))


def described(settings):
    """One line: `section.key=value; ...`."""
    return "; ".join(f"{s}.{k}={v}" for s, kv in settings.items() for k, v in kv.items())
