#!/usr/bin/env python3
"""Counts gtest / rostest cases in the JUnit XML files under a folder and prints
"N passed, N failed" as the last line. Exit status 1 if any failed or nothing ran.
A marker file '*.failed' in the folder counts as one failure (a build that broke, tests that
did not run); its text says what."""
import glob
import os
import sys
import xml.etree.ElementTree as ET


def main(root):
    passed = failed = skipped = 0
    per_file = []
    for path in sorted(glob.glob(os.path.join(root, "**", "*.xml"), recursive=True)):
        try:
            tree = ET.parse(path)
        except ET.ParseError as e:
            print(f"{os.path.relpath(path, root)}: unreadable result file ({e}); counted as a failure")
            failed += 1
            continue
        p = f = s = 0
        for case in tree.iter("testcase"):
            problem = case.find("failure")
            if problem is None:
                problem = case.find("error")
            if problem is not None:
                f += 1
                print(f"FAILED: {case.get('classname')}.{case.get('name')} ({os.path.relpath(path, root)})")
                # What the assertion said (CI shows only the end of the log): a few lines of it.
                text = (problem.get("message") or problem.text or "").strip().splitlines()
                for line in text[:6]:
                    print(f"    {line[:300]}")
            elif case.find("skipped") is not None or case.get("status") == "notrun":
                s += 1
            else:
                p += 1
        # rostest writes a testsuite with errors but no testcase when the node under test dies.
        for suite in tree.iter("testsuite"):
            if len(list(suite.iter("testcase"))) == 0 and int(suite.get("errors", 0) or 0) + int(suite.get("failures", 0) or 0) > 0:
                f += 1
                print(f"FAILED: {suite.get('name')} ran no test case ({os.path.relpath(path, root)})")
        per_file.append((os.path.relpath(path, root), p, f, s))
        passed, failed, skipped = passed + p, failed + f, skipped + s
    for marker in sorted(glob.glob(os.path.join(root, "*.failed"))):
        with open(marker) as f:
            print(f"FAILED: {f.read().strip()}")
        failed += 1
    for name, p, f, s in per_file:
        print(f"  {name}: {p} passed, {f} failed, {s} skipped")
    line = f"{passed} passed, {failed} failed"
    if skipped:
        line += f", {skipped} skipped"
    print(line)
    return 1 if failed or passed == 0 else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else "."))
