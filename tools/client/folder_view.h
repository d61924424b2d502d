// prism-client view DIR: the live 3D view of a finished session's folder (the --out folder of
// `prism-client stream` or `fetch`: chunks/*.drc, chunks.json, trajectory.txt, summary.json).
#pragma once

#include <atomic>
#include <string>

namespace prism {

// Serves DIR's map chunks and trajectory on `address` (HOST:PORT) until `stop` is set (SIGINT);
// returns the exit code (1 with a message on stderr for a folder without chunks or a bad address).
// The camera's frustum uses DIR/camera.yaml when there is one.
int ServeFolderView(const std::string& dir, const std::string& address, const std::atomic<bool>& stop);

}  // namespace prism
