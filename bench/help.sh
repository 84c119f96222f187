# Sourced first by the bench shell scripts with their arguments: given -h or --help, the script prints its header
# comment (its usage) and exits, instead of taking "--help" for a dataset or a runs folder.
case ${1:-} in -h | --help) sed -n '2,/^[^#]/s/^# \{0,1\}//p' "$0"; exit 0 ;; esac
