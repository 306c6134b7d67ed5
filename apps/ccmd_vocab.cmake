ccmd_add_executable(ccmd_vocab SOURCES ccmd_vocab.cc DEPS ccmd_features_training ccmd_util ccmd_app_common)

# The default place-recognition vocabulary, trained at build time from synthetic rooms the
# project renders itself, so that no data file sits in the repository and the server works
# out of the box (choice and measurements: docs/place_recognition.md). Programs find it with
# ccmd::app::DefaultVocabularyPath(); $CCMD_VOCABULARY overrides it. It is retrained only when
# missing or when the vocabulary code changes (not on every relink of ccmd_vocab).
option(CCMD_BUILD_VOCABULARY "Train the default place-recognition vocabulary at build time" ON)
set(CCMD_DEFAULT_VOCABULARY ${PROJECT_BINARY_DIR}/share/ccmd_vocabulary_default.bin)
target_compile_definitions(ccmd_app_common INTERFACE
  CCMD_DEFAULT_VOCABULARY="${CCMD_DEFAULT_VOCABULARY}")
if(CCMD_BUILD_VOCABULARY)
  add_custom_command(OUTPUT ${CCMD_DEFAULT_VOCABULARY}
    COMMAND ${CMAKE_COMMAND} -E make_directory ${PROJECT_BINARY_DIR}/share
    COMMAND ccmd_vocab_app --out ${CCMD_DEFAULT_VOCABULARY} --k 10 --depth 5 --seed 1 --threads 2
            --synth frames=480,seed=101,step=4 --synth frames=480,seed=102,step=4
            --synth frames=480,seed=103,step=4
            --json ${PROJECT_BINARY_DIR}/share/ccmd_vocabulary_default.json
    DEPENDS ${PROJECT_SOURCE_DIR}/libccmd/features/bow_vocabulary.cc
            ${PROJECT_SOURCE_DIR}/libccmd/features/bow_vocabulary.h
    COMMENT "Training the default place-recognition vocabulary (3 synthetic rooms, ~30 s)"
    VERBATIM)
  add_custom_target(ccmd_default_vocabulary ALL DEPENDS ${CCMD_DEFAULT_VOCABULARY})
endif()
