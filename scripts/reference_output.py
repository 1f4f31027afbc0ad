"""The output convention of this folder's reference scripts (read by `motionscale bench`)."""
import json


def emit(out, path):
    """Print `out` as one JSON line and, when `path` is given, write it there too."""
    print(json.dumps(out))
    if path:
        with open(path, "w") as f:
            json.dump(out, f, indent=1)
