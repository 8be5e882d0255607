#!/bin/sh
# A real Prometheus (Debian package "prometheus") on loopback scraping
# drivegate on its simulator, with the alert rules of alerts.yml loaded:
# a fault is injected into the simulated drive "lift" and the run shows
# DriveFault firing, then checks that every Grafana dashboard query is
# answered. Everything listens on 127.0.0.1 and is stopped at the end.
#
#   deploy/prometheus/demo.sh
#
# To look around by hand instead, on the machine running drivegate:
#   drivegate serve &                      # simulator, HTTP on 127.0.0.1:8080
#   prometheus --config.file=deploy/prometheus/prometheus.yml \
#              --storage.tsdb.path=/tmp/drivegate-prometheus
#   # then http://127.0.0.1:9090/alerts and /graph
set -eu
cd "$(dirname "$0")/../.."
command -v prometheus >/dev/null || { echo "needs prometheus (apt-get install prometheus)" >&2; exit 1; }
exec cargo test --test e2e deploy::prometheus::real_prometheus -- --nocapture
