#!/bin/bash
# Makes a development certificate authority and one certificate per process,
# for running behaviorlib with mutual TLS (--tls-cert, --tls-key, --tls-ca).
#
#   scripts/make-dev-certs.sh [--out DIR] [--days N] [--readable-keys] [NAME ...]
#
# DIR (default deploy/certs, which git ignores) receives:
#   ca.pem, ca.key              the CA (keep ca.key private; it signs)
#   NAME.pem, NAME.key          a certificate and key per NAME
# NAME defaults to every process of the compose deployment (its service
# names, drone1 and drone2), plus "operator" (behaviorctl, grpcurl, the
# launcher) and "prometheus" (the scraper). Each certificate's subject
# alternative names are DNS:NAME, DNS:localhost, IP:127.0.0.1 and
# URI:behaviorlib:NAME, so it serves under its compose name and on loopback;
# the URI is the identity that a policy names.
#
# Existing files are kept (the CA too), so the script can add a name later.
# With --expired, the certificates made are already expired (for tests).
# Keys are readable by their owner only; --readable-keys makes the processes'
# keys (not the CA's) readable by all, for the compose deployment, whose
# containers run as uid 10001 and mount them from the host:
#
#   scripts/make-dev-certs.sh --readable-keys
#   docker compose -f deploy/compose/docker-compose.yml up -d
#
#
# Development only: a fleet's certificates come from its own PKI.
set -euo pipefail

out="$(cd "$(dirname "$0")/.." && pwd)/deploy/certs"
days=825
expired=0
readable=0
names=()
while [[ $# -gt 0 ]]; do
  case "$1" in
    --out) out="$2"; shift 2 ;;
    --days) days="$2"; shift 2 ;;
    --expired) expired=1; shift ;;
    --readable-keys) readable=1; shift ;;
    -h|--help) sed -n '2,20p' "$0"; exit 0 ;;
    -*) echo "make-dev-certs: unknown option $1" >&2; exit 2 ;;
    *) names+=("$1"); shift ;;
  esac
done
if [[ ${#names[@]} -eq 0 ]]; then
  names=(channel-broker simulator coordinator console operator admin prometheus)
  for robot in drone1 drone2; do
    for system in basic-quadrotor-behaviors quadrotor-motion-with-pid-control \
        quadrotor-motion-with-mpc-control quadrotor-motion-with-platform-control \
        multi-sensor-fusion navigation-with-lidar attention-to-visual-markers \
        swarm-interaction operator-interaction; do
      names+=("$robot-$system")
    done
  done
fi

command -v openssl > /dev/null || { echo "make-dev-certs: openssl is not installed" >&2; exit 1; }
mkdir -p "$out"
chmod 700 "$out"
umask 077

if [[ ! -f "$out/ca.pem" || ! -f "$out/ca.key" ]]; then
  openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes \
    -keyout "$out/ca.key" -out "$out/ca.pem" -days "$days" \
    -subj "/O=behaviorlib development/CN=behaviorlib development CA" \
    -addext "basicConstraints=critical,CA:TRUE" \
    -addext "keyUsage=critical,keyCertSign,cRLSign" 2> /dev/null
  echo "make-dev-certs: CA $out/ca.pem"
fi

# openssl ca (rather than x509 -req) sets any validity period, past ones too.
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
touch "$work/index.txt"
cat > "$work/ca.cnf" <<CNF
[ca]
default_ca = dev
[dev]
database = $work/index.txt
new_certs_dir = $work
serial = $work/serial
certificate = $out/ca.pem
private_key = $out/ca.key
default_md = sha256
policy = any
copy_extensions = copy
unique_subject = no
[any]
commonName = supplied
organizationName = optional
CNF

for name in "${names[@]}"; do
  if [[ ! "$name" =~ ^[A-Za-z0-9._-]+$ ]]; then
    echo "make-dev-certs: '$name' is not a valid name (letters, digits, . _ -)" >&2
    exit 2
  fi
  if [[ -f "$out/$name.pem" && -f "$out/$name.key" && $expired -eq 0 ]]; then continue; fi
  openssl req -new -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes \
    -keyout "$out/$name.key" -out "$work/$name.csr" \
    -subj "/O=behaviorlib development/CN=$name" \
    -addext "subjectAltName=DNS:$name,DNS:localhost,IP:127.0.0.1,URI:behaviorlib:$name" \
    -addext "extendedKeyUsage=serverAuth,clientAuth" 2> /dev/null
  if [[ $expired -eq 1 ]]; then
    dates=(-startdate 20200101000000Z -enddate 20200102000000Z)
  else
    dates=(-days "$days")
  fi
  openssl rand -hex 16 > "$work/serial"
  openssl ca -batch -config "$work/ca.cnf" -notext "${dates[@]}" \
    -in "$work/$name.csr" -out "$out/$name.pem" 2> "$work/ca.log" \
    || { cat "$work/ca.log" >&2; exit 1; }
  echo "make-dev-certs: $out/$name.pem"
done
if [[ $readable -eq 1 ]]; then
  chmod 755 "$out"
  chmod 644 "$out"/*.pem
  for name in "${names[@]}"; do chmod 644 "$out/$name.key"; done
fi
