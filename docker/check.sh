#!/usr/bin/env bash
# make docker-check: build the CPU variant of docker/Dockerfile for real on this machine and run it.
# No image registry is reachable here, so the base image is made from Debian packages (debootstrap), and the build
# uses the host's own pip sources (local CPU torch wheels and index). These are facts of this machine: they live in
# this script, never in the Dockerfile users build. Needs root (or rootless podman), ~2 GB of disk, a few minutes.
set -euo pipefail
cd "$(dirname "$0")/.."
WORK=${WORK:-/tmp/anycity-docker-check}
BASE_TAG=localhost/debian-python:bookworm
TAG=localhost/anycity:cpu-check
MIRROR=${MIRROR:-http://deb.debian.org/debian}
mkdir -p "$WORK"

need=()
for tool in podman buildah debootstrap runc; do command -v "$tool" >/dev/null || need+=("$tool"); done
if ((${#need[@]})); then
    echo "docker-check: installing ${need[*]}"
    apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q podman buildah debootstrap runc
fi

# Options this machine needs: runc, explicit ulimits (the defaults are refused here)
export CONTAINERS_CONF="$WORK/containers.conf"
cat > "$CONTAINERS_CONF" <<CONF
[engine]
runtime = "runc"
[containers]
default_ulimits = ["nofile=4096:4096", "nproc=4096:4096"]
CONF

if ! podman image exists "$BASE_TAG"; then
    echo "docker-check: debootstrap bookworm base (about a minute)"
    rm -rf "$WORK/rootfs"
    debootstrap --variant=minbase --include=python3,python3-venv,python3-pip,ca-certificates bookworm \
        "$WORK/rootfs" "$MIRROR" >"$WORK/debootstrap.log"
    tar -C "$WORK/rootfs" -c . | podman import - "$BASE_TAG"
fi

# The host's pip sources, mounted read-only at the same paths: local CPU torch wheels, the local index, the CA bundle
cat > "$WORK/pip.conf" <<CONF
[global]
$(pip_conf=$(python3 -m pip config list 2>/dev/null || true); echo "$pip_conf" | sed -n \
    -e "s/^global\.find-links='\(.*\)'/find-links = \1/p" -e "s/^global\.extra-index-url='\(.*\)'/extra-index-url = \1/p")
cert = /etc/ssl/certs/ca-certificates.crt
CONF
mounts=(-v "$WORK/pip.conf:/etc/pip.conf:ro" -v /etc/ssl/certs/ca-certificates.crt:/etc/ssl/certs/ca-certificates.crt:ro)
for d in /opt/wheels /opt/pypi /opt/pypi-more; do [[ -d $d ]] && mounts+=(-v "$d:$d:ro"); done

echo "docker-check: podman build (CPU variant of docker/Dockerfile)"
podman build --format docker --network host "${mounts[@]}" -f docker/Dockerfile -t "$TAG" \
    --build-arg BASE="$BASE_TAG" --build-arg WITH_GSPLAT=0 --build-arg EXTRAS=wan,cpu,dev \
    --build-arg TORCH_INDEX_URL=file:///opt/pypi/simple .

echo "docker-check: anycity --help"
podman run --rm --network none "$TAG" --help | head -5
echo "docker-check: the tiny end-to-end test inside the image (fit -> test -> predict, Stage I and II)"
podman run --rm --network none --entrypoint python -w /work "$TAG" \
    -m pytest -q -p no:cacheprovider --rootdir /opt/anycity /opt/anycity/tests/integration/test_cli_tiny.py -k stage1_then_stage2
echo "docker-check: OK"
