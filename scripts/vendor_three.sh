#!/usr/bin/env bash
# Vendor three.js into the web app at a pinned version, from the npm registry: the page
# loads nothing from a CDN. Usage: scripts/vendor_three.sh 0.171.0
set -euo pipefail
version="${1:?usage: $0 VERSION}"
out="$(cd "$(dirname "$0")/.." && pwd)/app/web/vendor/three"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
(cd "$tmp" && npm pack --silent "three@$version" >/dev/null && tar xzf "three-$version.tgz")
mkdir -p "$out"
cp "$tmp/package/build/three.module.min.js" "$tmp/package/build/three.core.min.js" \
   "$tmp/package/examples/jsm/controls/OrbitControls.js" "$tmp/package/LICENSE" "$out/"
cat > "$out/VERSION" <<END
three $version, from the npm registry (npm pack three@$version), MIT licence (LICENSE).
Files: build/three.module.min.js, build/three.core.min.js, examples/jsm/controls/OrbitControls.js.
Refresh with scripts/vendor_three.sh VERSION.
END
echo "three $version vendored in $out"
