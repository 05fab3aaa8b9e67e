#!/usr/bin/env bash
# System packages clothgap uses when it can: libLLVM 16+ lets Mitsuba run its
# llvm_ad_rgb variant (2-3x faster than scalar_rgb on CPU). Without it the
# renderer falls back to scalar_rgb, so a failure here is a warning, not an error.
set -u
have_llvm() { ls /usr/lib/*/libLLVM.so.1[6-9]* /usr/lib/*/libLLVM-1[6-9].so /usr/lib/*/libLLVM.so.[2-9][0-9]* 2>/dev/null | grep -q .; }
if have_llvm; then exit 0; fi
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  echo "installing libllvm19 (Mitsuba's llvm_ad_rgb backend)"
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19) >/dev/null 2>&1 \
    || echo "warning: could not install libllvm19; Mitsuba will use scalar_rgb (slower)"
else
  echo "warning: no libLLVM 16+ found and cannot apt-get as $(id -un); Mitsuba will use scalar_rgb (slower)." \
       "Install libllvm19 (Debian/Ubuntu) for the llvm_ad_rgb backend."
fi
exit 0
