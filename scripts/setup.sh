# Sourced by scripts/run.sh and scripts/test.sh: makes sure this Debian/Ubuntu machine has what
# Isowall needs (a Rust toolchain, a Vulkan loader and driver), installing it with apt when run as
# root, else printing the exact command and stopping.

need_pkgs=()
missing_why=()

if ! command -v cargo >/dev/null 2>&1; then
    echo "isowall: cargo (Rust) is not installed. Install a Rust toolchain first, e.g.:" >&2
    echo "    curl --proto '=https' --tlsv1.2 -sSf https://sh.rustup.rs | sh   (then: . \"\$HOME/.cargo/env\")" >&2
    echo "or: apt-get install cargo   (Rust 1.91 or newer is needed: zarrs, the OME-Zarr reader, needs it)" >&2
    exit 1
fi
rust_version=$(rustc --version 2>/dev/null | awk '{print $2}')
if [ -n "$rust_version" ] && ! printf '1.91.0\n%s\n' "$rust_version" | sort -V -C; then
    echo "isowall: Rust $rust_version is too old: 1.91 or newer is needed, for zarrs (rustup update, or a newer cargo package)" >&2
    exit 1
fi

# The test suite checks the house's lints and formatting (clippy and rustfmt, rustup's components
# of the same toolchain). Lints change between toolchains: they were last checked clean on this
# one, and on another its new lints are reported without failing the run.
lints_checked_on=1.95.0
if [ "${isowall_tests:-}" = yes ]; then
    for tool in clippy fmt; do
        if ! cargo "$tool" --version >/dev/null 2>&1; then
            comp=$([ "$tool" = fmt ] && echo rustfmt || echo clippy)
            echo "isowall: cargo $tool is missing (the tests check the lints and formatting with it): rustup component add $comp" >&2
            exit 1
        fi
    done
    if [ "$rust_version" = "$lints_checked_on" ]; then
        clippy_strict=yes
    else
        clippy_strict=no
        echo "isowall: the lints were checked on Rust $lints_checked_on; this is $rust_version, so clippy's findings are shown without failing the run" >&2
    fi
fi

# The Vulkan loader.
if ! ldconfig -p 2>/dev/null | grep -q 'libvulkan\.so\.1'; then
    need_pkgs+=(libvulkan1)
    missing_why+=("the Vulkan loader (libvulkan.so.1)")
fi
# A Vulkan driver: any installed ICD manifest will do (a GPU's, or Mesa's lavapipe).
have_icd=no
for d in /usr/share/vulkan/icd.d /etc/vulkan/icd.d /usr/local/share/vulkan/icd.d; do
    if ls "$d"/*.json >/dev/null 2>&1; then have_icd=yes; fi
done
if [ -n "${VK_DRIVER_FILES:-}${VK_ICD_FILENAMES:-}" ]; then have_icd=yes; fi
if [ "$have_icd" = no ]; then
    need_pkgs+=(mesa-vulkan-drivers)
    missing_why+=("a Vulkan driver (Mesa's software driver lavapipe, where there is no GPU driver)")
fi

# Build dependencies: gilrs (gamepads in `isowall session`) reads devices through libudev and
# links it at build time (pkg-config finds libudev.pc from libudev-dev).
if ! { command -v pkg-config >/dev/null 2>&1 && pkg-config --exists libudev; }; then
    command -v pkg-config >/dev/null 2>&1 || { need_pkgs+=(pkg-config); missing_why+=("pkg-config (build)"); }
    need_pkgs+=(libudev-dev)
    missing_why+=("libudev's headers (libudev-dev, to build gamepad input)")
fi

# C and C++ compilers: zarrs' blosc, zstd, lz4 and snappy codecs (OME-Zarr stores) build their
# C libraries.
if ! { command -v cc && command -v c++; } >/dev/null 2>&1; then
    need_pkgs+=(gcc g++)
    missing_why+=("C and C++ compilers (to build the OME-Zarr codecs' libraries)")
fi

# The test suite (scripts/test.sh sets isowall_tests=yes) also shows a node's tiles in a window:
# a virtual X server (Xvfb), X screenshots (xwd, in x11-apps) and the X11 libraries that winit
# loads at run time; a browser with its WebDriver for the console's page; and Prometheus's
# promtool and server for the metrics.
if [ "${isowall_tests:-}" = yes ]; then
    command -v Xvfb >/dev/null 2>&1 || { need_pkgs+=(xvfb); missing_why+=("Xvfb (for the window test)"); }
    command -v xwd >/dev/null 2>&1 || { need_pkgs+=(x11-apps); missing_why+=("xwd (for the window test)"); }
    # The operator console's browser test drives Debian's chromium through chromedriver.
    command -v chromium >/dev/null 2>&1 || { need_pkgs+=(chromium); missing_why+=("chromium (for the console's browser test)"); }
    command -v chromedriver >/dev/null 2>&1 || { need_pkgs+=(chromium-driver); missing_why+=("chromedriver (for the console's browser test)"); }
    # The metrics' test checks /metrics with promtool and has a real prometheus scrape it.
    { command -v promtool && command -v prometheus; } >/dev/null 2>&1 || { need_pkgs+=(prometheus); missing_why+=("promtool and prometheus (for the metrics' test)"); }
    # The packaged units are checked with systemd-analyze verify.
    command -v systemd-analyze >/dev/null 2>&1 || { need_pkgs+=(systemd); missing_why+=("systemd-analyze (for the units' test)"); }
    # The Debian package's test checks the package with lintian (dpkg-deb comes with dpkg).
    command -v lintian >/dev/null 2>&1 || { need_pkgs+=(lintian); missing_why+=("lintian (for the package's test)"); }
    for lib in libX11-xcb.so.1:libx11-xcb1 libXcursor.so.1:libxcursor1 libXi.so.6:libxi6 \
               libxkbcommon-x11.so.0:libxkbcommon-x11-0; do
        if ! ldconfig -p 2>/dev/null | grep -q "${lib%%:*}"; then
            need_pkgs+=("${lib##*:}")
            missing_why+=("${lib%%:*} (for the window test)")
        fi
    done
fi

if [ ${#need_pkgs[@]} -gt 0 ]; then
    echo "isowall: missing ${missing_why[*]}" >&2
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
        echo "isowall: installing ${need_pkgs[*]} with apt-get" >&2
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -qq && apt-get install -y -qq --no-install-recommends "${need_pkgs[@]}" >&2 || {
            echo "isowall: apt-get install ${need_pkgs[*]} failed; install them and run this again" >&2
            exit 1
        }
    else
        echo "isowall: install them first (as root):" >&2
        echo "    sudo apt-get install ${need_pkgs[*]}" >&2
        exit 1
    fi
fi

# The Debian package's test makes the package with cargo-deb (a cargo subcommand, from crates.io,
# built here: about 3 minutes on 2 cores, so only where it is missing; the version the test was
# written against, with its own lock file).
if [ "${isowall_tests:-}" = yes ] && ! cargo deb --version >/dev/null 2>&1; then
    echo "isowall: installing cargo-deb (for the package's test): cargo install cargo-deb@3.8.0 --locked" >&2
    cargo install --quiet cargo-deb@3.8.0 --locked >&2 || {
        echo "isowall: cargo install cargo-deb failed; install it (cargo install cargo-deb --locked) and run this again" >&2
        exit 1
    }
fi

# Mesa's window-system code warns without a runtime dir; headless runs do not need a real one.
if [ -z "${XDG_RUNTIME_DIR:-}" ] || [ ! -d "${XDG_RUNTIME_DIR}" ]; then
    XDG_RUNTIME_DIR=$(mktemp -d "${TMPDIR:-/tmp}/isowall-xdg.XXXXXX")
    export XDG_RUNTIME_DIR
fi
