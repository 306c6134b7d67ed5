# Dense map benchmark: store update cost against a naive rebuild, reconstruction error.
if(CCMD_BUILD_BENCHMARKS)
  ccmd_add_executable(ccmd_dense_bench SOURCES ccmd_dense_bench.cc dense_bench_revisits.cc
    DEPS ccmd_codec ccmd_dense ccmd_synth ccmd_eval ccmd_app_common opencv_imgproc)
endif()
